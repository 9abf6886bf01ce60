"""``python experiments/learn.py [overrides]``: the ``torchflow-learn`` command (:mod:`torchflow.learn`,
whose docstring has examples) from a source checkout."""

from torchflow.learn import main

if __name__ == "__main__":
    main()
