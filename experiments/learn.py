"""``python experiments/learn.py [overrides]``: the ``torchflow-learn`` command (:mod:`torchflow.app.learn`,
whose docstring has examples) from a source checkout."""

from torchflow.app.learn import main

if __name__ == "__main__":
    main()
