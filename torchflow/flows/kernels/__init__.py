"""The compiled kernels beneath the flows: fused CPU (Numba) and GPU (Triton) pseudo-steps and
the particle filter's weighting kernel.

May import: :mod:`torchflow.core` only (not the flows above it: a kernel is handed tensors and
the choices made for it).

* :mod:`~torchflow.flows.kernels.steps`: the kernels' set-up and calls, with their maths;
* :mod:`~torchflow.flows.kernels.cpu`, :mod:`~torchflow.flows.kernels.cpu_weights` (Numba) and
  :mod:`~torchflow.flows.kernels.gpu` (Triton): the compiled code, imported only when used (the
  ``kernels`` extra).

Whether a kernel runs is decided in one module, :mod:`torchflow.flows.select`, which reads the
declarations of flows, measurements, models, proposals and filters and the kernels' tuning knobs;
:mod:`torchflow.flows.loops` drives the chosen kernel through pseudo-time. Filters and the runner
ask :mod:`~torchflow.flows.select` and import nothing from here. The reference loop
(:func:`torchflow.flows.integrate_flow`) is what runs otherwise, and the kernels agree with it to
round-off.
"""
