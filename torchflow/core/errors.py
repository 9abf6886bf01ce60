"""torchflow's error types.

Every refusal of a bad argument, setting or model output raises one of these, so a caller can catch
torchflow's own answers (``except torchflow.TorchflowError``) apart from a bug's raw torch error.
They subclass the built-in types that the same checks raised before (``ValueError``, ``TypeError``,
``FloatingPointError``), so ``except ValueError`` keeps working.

- :class:`ArgumentError` (a ``ValueError``): a value, shape, size or setting that cannot be used;
  the message names the argument, what was expected and what arrived.
- :class:`ArgumentTypeError` (a ``TypeError``): the wrong kind of object (a string for a model, a
  float tensor of the wrong dtype).
- :class:`NonFiniteError` (a ``FloatingPointError``): a filter produced a NaN or infinite value; the
  message and attributes name the filter, the quantity, the time step and the trials.
"""

from __future__ import annotations

from typing import Optional, Sequence


class TorchflowError(Exception):
    """Base class of every error torchflow raises on purpose."""


class ArgumentError(TorchflowError, ValueError):
    """A bad value, shape, size or setting; the message names the argument."""


class ArgumentTypeError(TorchflowError, TypeError):
    """An argument of the wrong type or dtype; the message names the argument."""


class NonFiniteError(TorchflowError, FloatingPointError):
    """A filter produced a NaN or infinite value.

    Attributes:
        filter_name: name of the filter that produced it.
        step: 1-based time step (0 where the quantity is not tied to a step, e.g. a gradient).
        trials: indices of the offending trials (within the batch that was being filtered).
        what: the quantity ("estimate", "log-evidence increment", "gradient of psi", ...).
        hint: what to look at or change, in brackets after the rest (``None``: nothing).
    """

    def __init__(
        self, filter_name: str, step: int, trials: Sequence[int], what: str = "estimate", hint: Optional[str] = None
    ):
        self.filter_name = filter_name
        self.step = step
        self.trials = list(trials)
        self.what = what
        self.hint = hint
        shown = self.trials[:10]
        more = "" if len(self.trials) <= 10 else f" (and {len(self.trials) - 10} more)"
        where = f" at time step {step}" if step else ""
        which = f" in trial(s) {shown}{more}" if self.trials else ""
        advice = f" ({hint})" if hint else ""
        super().__init__(f"{filter_name}: non-finite {what}{where}{which}{advice}")

    def __reduce__(self):  # picklable across processes (joblib sweeps, DDP)
        return (type(self), (self.filter_name, self.step, self.trials, self.what, self.hint))
