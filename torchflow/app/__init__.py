"""The application: everything a command runs, above the library.

May import: every torchflow package (nothing below imports this one).

* :mod:`.cli`: the ``torchflow`` command (``python -m torchflow``);
* :mod:`.tasks`: what a run does besides filtering (smoothing, parameter inference, learning
  tasks) and how each is scored;
* :mod:`.runner`: the Monte Carlo runner (plan, execute, score, checkpoints, result files,
  figures, sweeps, the command shell); :func:`torchflow.app.runner.run_experiment` is its
  Python entry;
* :mod:`.data`: recorded observations (CSV, NumPy, torch files) and declared priors;
* :mod:`.learn`: the ``torchflow-learn`` command; :mod:`.lightning`: the Lightning module it
  trains (usable alone in a learning pipeline).
"""
