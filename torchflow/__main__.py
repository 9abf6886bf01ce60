"""``python -m torchflow [overrides]``: the command line (:mod:`torchflow.cli`)."""

from .cli import main

if __name__ == "__main__":
    main(prog="python -m torchflow")
