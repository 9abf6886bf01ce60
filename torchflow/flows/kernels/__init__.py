"""The kernel layer of the flows: fused CPU (Numba) and GPU (Triton) pseudo-steps and the one
module that chooses them.

* :mod:`~torchflow.flows.kernels.select`: which kernel runs (every eligibility rule, and the only
  reader of the kernels' tuning knobs);
* :mod:`~torchflow.flows.kernels.loops`: the pseudo-time loops that drive a chosen kernel;
* :mod:`~torchflow.flows.kernels.steps`: the kernels' set-up and calls, with their maths;
* :mod:`~torchflow.flows.kernels.graph_step`: a particle filter's whole time step replayed from a
  CUDA graph (the random draws split into words made outside the graph);
* :mod:`~torchflow.flows.kernels.cpu` (Numba) and :mod:`~torchflow.flows.kernels.gpu` (Triton):
  the compiled code, imported only when used (the ``kernels`` extra).

Nothing outside this package decides whether a kernel runs; the reference loop
(:func:`torchflow.flows.integrate_flow`) is what runs otherwise, and the kernels agree with it to
round-off.
"""
