"""The command line from a source checkout: ``python experiments/run.py [overrides]`` is the
installed ``torchflow`` command (:mod:`torchflow.cli`), with the same configs (``configs/``).

    python experiments/run.py                                   # default acoustic comparison
    python experiments/run.py model=linear_gaussian filter=[kf,bpf] trials=100 steps=10 n_particles=200
    python experiments/run.py experiment=seed000_table1         # a paper table
    python experiments/run.py -m filter=[bpf] n_particles=100,1000   # sweep; one folder per job
"""
from torchflow.cli import main

if __name__ == "__main__":
    main(prog="python experiments/run.py")
