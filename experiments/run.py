"""``python experiments/run.py [overrides]``: the ``torchflow`` command (:mod:`torchflow.app.cli`, whose
docstring has examples) from a source checkout, with the same configs (``configs/``)."""

from torchflow.app.cli import main

if __name__ == "__main__":
    main()  # the resume hint repeats the script as invoked (python ../experiments/run.py from another folder)
