# read as pkg://torchflow.configs (an installed copy): register the signature nodes its configs extend
__import__("torchflow.core.registry").core.registry.register_configs()
