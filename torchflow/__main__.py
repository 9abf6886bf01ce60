"""``python -m torchflow [overrides]``: the command line (:mod:`torchflow.app.cli`)."""

from torchflow.app.cli import main

if __name__ == "__main__":
    main(prog="python -m torchflow")
