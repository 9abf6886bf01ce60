# read as pkg://torchflow.configs (an installed copy): the signature nodes its configs extend
from torchflow.registry import register_configs

register_configs()
