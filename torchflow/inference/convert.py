"""Draws of the particle MCMC samplers as an ArviZ object (the optional ``arviz`` extra)."""

from __future__ import annotations

from torchflow.core.errors import ArgumentTypeError


def to_arviz(result):
    """``result`` (a :class:`~torchflow.inference.PMMHResult`, or any result with ``samples``
    name -> ``(C, S, *shape)`` and ``log_likelihood (C, S)``) as ArviZ's container of draws
    (``arviz.from_dict``: an ``InferenceData`` with the groups ``posterior``, one variable per
    parameter with dims ``(chain, draw, *shape)``, and ``sample_stats``, whose ``log_likelihood_estimate`` is
    the filter's estimate at each draw), for ArviZ's summaries and plots (``arviz.summary``,
    ``arviz.plot_trace``).

    Raises:
        ImportError: ArviZ is not installed (``pip install torchflow[arviz]``).
    """
    try:
        import arviz
    except ImportError as e:
        raise ImportError(
            "to_arviz needs ArviZ, the optional extra 'arviz': pip install 'torchflow[arviz]' (or pip install arviz)"
        ) from e
    samples, ll = getattr(result, "samples", None), getattr(result, "log_likelihood", None)
    if not isinstance(samples, dict) or ll is None:
        raise ArgumentTypeError(f"result: expected a PMMHResult (samples, log_likelihood), got {type(result).__name__}")
    posterior = {name: v.detach().double().cpu().numpy() for name, v in samples.items()}
    stats = {"log_likelihood_estimate": ll.detach().double().cpu().numpy()}
    return arviz.from_dict(posterior=posterior, sample_stats=stats)


__all__ = ["to_arviz"]
