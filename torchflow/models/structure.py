"""What a model declares about itself, in one record, as plain data.

Filters, the flow kernels and the chunk planner read a model's :class:`Structure`; nothing is
detected from values at run time (a declaration that is wrong gives wrong numbers, as a wrong
model would). A model class states it once::

    class MyModel(GaussianStateSpaceModel):
        structure = Structure(linear_dynamics=True, measurement_noise="scalar")

and a model whose structure depends on its arguments refines it per instance with
``self.structure = dataclasses.replace(type(self).structure, ...)``.

Two fields promise more than the equations: :attr:`Structure.graph_safe` and
:attr:`Structure.measurement_form` tell the kernel layer that the model's own code may be replaced
by a captured graph or a kernel's arithmetic. They hold only for the class that declares the
record: a subclass that inherits its parent's record unchanged (it may have changed a method) gets
neither, until it declares a record of its own (:func:`kernel_structure`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional, Tuple

from torchflow.core.errors import ArgumentError

#: the declared structures of the measurement noise R
NOISE = ("scalar", "diagonal", "dense", "state_dependent", "state_dependent_diagonal")
#: the declared forms of the prior covariance
PRIOR = ("dense", "diagonal")


@dataclass(frozen=True)
class Structure:
    """A model's declared structure.

    Attributes:
        linear_dynamics: the transition mean is ``x F^T`` with ``F = transition_matrix()``: filters
            skip Jacobians and share the covariance recursions that cannot differ between particles.
        gaussian_transition: ``p(x_k | x_{k-1})`` is ``N(transition_mean, transition_cov)``; a model
            with another transition law (skewed-t) declares ``False`` and its Gaussian form is the fit
            that flows, trackers and stochastic-flow proposals use (the weights stay exact).
        linear_measurement: ``h(x) = x H^T`` with ``H = measurement_matrix()``.
        gaussian_measurement: ``p(z_k | x_k)`` is ``N(measure(x), measurement_cov(x))``; a model with
            another measurement law (Poisson counts) declares ``False``: its Gaussian form is then the
            fit that flows and trackers use, and the density of a partly observed measurement
            (NaN coordinates) is the model's own
            (:meth:`~torchflow.models.StateSpaceModel.measurement_log_prob_observed`).
        measurement_noise: the structure of R, one of :data:`NOISE`: ``"scalar"`` (``sigma^2 I``,
            constant), ``"diagonal"``, ``"dense"`` (constant), ``"state_dependent"`` (varies with x)
            or ``"state_dependent_diagonal"`` (varies with x, diagonal: whitening is a division).
        measurement_support: the state coordinates h reads (``None``: all): the flows then linearise
            in that k-dimensional subspace, exactly.
        measurement_jacobian_diagonal: ``m == d`` and ``dh_i/dx_j = 0`` for ``i != j``.
        transition_matrix_scale: ``c`` when the constant transition matrix is exactly ``c I``.
        measurement_matrix_scale: ``c`` when the constant measurement matrix is exactly ``c I``.
        measurement_noise_scale: ``r`` when the constant R is exactly ``r I``.
        measurement_form: a named form of h that a flow kernel linearises itself, ``(name, names of
            the model's tensors it reads)``; ``("inverse_distance_sum", ("sensors", "psi", "d0"))``
            declares ``h_i(x) = psi sum_c 1 / (|p_c - s_i| + d0)`` over the 2-D positions ``p_c``
            (the support's coordinate pairs) and sensors ``s_i (m, 2)``, with a scalar R.
        graph_safe: sampling and densities are pure functions of their tensors that draw only
            through the passed generator's ``normal``/``uniform``, with no host read and no
            Python-side state: a particle filter's whole step may be replayed from a CUDA graph.
        has_positions: the state holds target positions (the model gives ``positions(x)
            -> (..., C, 2 or 3)``; position metrics such as OMAT apply).
        padded_measurements: the observations are measurement sets of varying size, padded, with a
            ``mask`` (TDOA localisation); only estimators declaring the same take them.
        bytes_per_point: rough memory of evaluating the model at one point (intermediates of
            ``measure``, log-densities), for the chunk planner; ``None``: ``32 (d + m)``.
        prior_covariance: the form of the prior covariance that :meth:`initial_belief` (and
            ``declared_prior``) return, one of :data:`PRIOR`: ``"dense"`` (a tensor ``(B, d, d)``)
            or ``"diagonal"`` (a :class:`~torchflow.core.covariances.DiagonalCovariance` of variances
            ``(B, d)``: no ``d x d`` matrix, for states of ``d = 10^5`` and more). The chunk planner
            sizes the priors by it.
        sites: the geometry the localising filters measure a radius in when no distances are given:
            ``"ring"`` (the state coordinates are sites ``0 .. d-1`` on a ring of period ``d``:
            Lorenz-96), or ``None``: the model's own ``site_distances() -> (d, d)`` where it has
            one (the sensor network's grid), else none (a finite radius then needs distances).
    """

    linear_dynamics: bool = False
    gaussian_transition: bool = True
    linear_measurement: bool = False
    gaussian_measurement: bool = True
    measurement_noise: str = "dense"
    measurement_support: Optional[Tuple[int, ...]] = None
    measurement_jacobian_diagonal: bool = False
    transition_matrix_scale: Optional[float] = None
    measurement_matrix_scale: Optional[float] = None
    measurement_noise_scale: Optional[float] = None
    measurement_form: Optional[tuple] = None
    graph_safe: bool = False
    has_positions: bool = False
    padded_measurements: bool = False
    bytes_per_point: Optional[int] = None
    prior_covariance: str = "dense"
    sites: Optional[str] = None

    def __post_init__(self):
        if self.sites not in (None, "ring"):
            raise ArgumentError(f"Structure: sites: expected None or 'ring', got {self.sites!r}")
        if self.measurement_noise not in NOISE:
            raise ArgumentError(
                f"Structure: measurement_noise: expected one of {NOISE}, got {self.measurement_noise!r}"
            )
        if self.prior_covariance not in PRIOR:
            raise ArgumentError(f"Structure: prior_covariance: expected one of {PRIOR}, got {self.prior_covariance!r}")
        if self.measurement_support is not None:
            object.__setattr__(self, "measurement_support", tuple(int(i) for i in self.measurement_support))

    def replace(self, **changes) -> "Structure":
        """A copy with ``changes``."""
        return replace(self, **changes)


def kernel_structure(model) -> Structure:
    """``model.structure`` with :attr:`~Structure.graph_safe` and :attr:`~Structure.measurement_form`
    kept only where the model's own class declares a record (see the module docstring)."""
    s = model.structure
    if "structure" in vars(type(model)):
        return s
    return s.replace(graph_safe=False, measurement_form=None)


def bytes_per_point(model) -> int:
    """The chunk planner's memory per evaluation point: the declared
    :attr:`~Structure.bytes_per_point`, else ``32 (d + m)``."""
    b = model.structure.bytes_per_point
    return int(b) if b is not None else 8 * 4 * (model.state_dim + model.obs_dim)
