"""Smoothing: the law of the states given all the observations, ``p(x_t | z_1:T)``.

One entry, :func:`smooth`, for every filter:

* ``"rts"``: the Rauch-Tung-Striebel smoother of the Kalman family (exact for the Kalman filter on
  a linear-Gaussian model; the extended and unscented RTS smoothers for the EKF and UKF), returning
  smoothed means and covariances;
* ``"ffbsi"``: forward filtering, backward simulation, for every particle filter whose model gives
  the transition density (the bootstrap PF, the PF-PF and the other proposals: their weighted
  particles are draws of the filtering law): ``M`` paths drawn backwards, ``O(N M)`` per step,
  in blocks of paths (``path_chunk``) to bound memory;
* ``"genealogy"``: the ancestral lines of the particle filter's final particles (no transition
  density needed, cheap, but the early steps collapse onto few ancestors: path degeneracy).

Paths are ``(B, M, T+1, d)`` with index 0 the initial state, and means ``(B, T+1, d)``.

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.filters`.
"""

from torchflow.smoothing.core import SMOOTHERS, SmoothingResult, ffbsi, genealogy, rts, smooth, smoothing_method

__all__ = ["smooth", "smoothing_method", "SmoothingResult", "rts", "ffbsi", "genealogy", "SMOOTHERS"]
