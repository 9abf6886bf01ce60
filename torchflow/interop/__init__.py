"""Adapters to other tracking frameworks (optional dependencies; the core never imports them).

* :mod:`torchflow.interop.stonesoup`: torchflow's particle flows as a Stone Soup ``Updater``
  (``pip install "torchflow[stonesoup]"``).

May import: every library floor below the application (:mod:`torchflow.core` to
:mod:`torchflow.filters`).
"""
