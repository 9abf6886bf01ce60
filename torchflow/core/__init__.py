"""Foundations: what every floor above uses, knowing nothing of models, flows or filters.

May import: torch, numpy (scipy, Triton and Hydra only inside the function that needs them).
Nothing here imports another torchflow package.

* :mod:`.errors`, :mod:`.checks`: the error types and the argument checks that raise them;
* :mod:`.linalg`, :mod:`.special`, :mod:`.linearize`: batched linear algebra (Cholesky solves,
  never an inverse), special functions, Jacobians by ``torch.func``;
* :mod:`.random`: per-trial random streams from one ``torch.Generator`` (and the Triton Philox
  kernel, :mod:`._philox_kernel`, :mod:`._triton`);
* :mod:`.resampling`: log-weights, effective sample size, resampling schemes, particle gathers;
* :mod:`.covariances`: covariance types (dense, diagonal, banded) and their estimators;
* :mod:`.geometry`: localisation geometry (the Gaspari-Cohn taper, a ring's distances, the
  observations within a radius of each coordinate in a model's declared geometry);
* :mod:`.constraints`: constrained parameters of learnable models;
* :mod:`.missing`: missing observations (NaN masks) and the context that declares them;
* :mod:`.trackers`: Gaussian belief updates (Kalman, EKF, UKF) on ``(..., d)`` beliefs;
* :mod:`.metrics`: the scores (RMSE, OMAT, OSPA, ESS, ...) and their registry;
* :mod:`.tuning`, :mod:`.registry`, :mod:`.progress`, :mod:`.blocks`, :mod:`.cudagraphs`,
  :mod:`.profiling`: tuning knobs, the name registry behind the configs, progress reports, blockwise
  evaluation, CUDA graph capture, operation counts;
* :mod:`.layers`: the floors of the package and the check that no import runs against them.
"""
