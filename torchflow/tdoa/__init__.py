"""Multi-object localisation from TDOA measurements: a wing built on the filters' parts.

May import: :mod:`torchflow.core`, :mod:`torchflow.models`, :mod:`torchflow.flows`,
:mod:`torchflow.proposals`, :mod:`torchflow.filters`.

* :mod:`.localisers`: the flow-induced mixture localiser (:class:`FlowMixtureLocaliser`) and the
  bootstrap localiser (:class:`BootstrapLocaliser`), whose output is sets of objects, not states;
* :mod:`.association`: loopy belief propagation for the measurement-to-object association.
"""

from torchflow.tdoa.association import Association, loopy_association
from torchflow.tdoa.localisers import (
    METHODS,
    BootstrapLocaliser,
    FlowMixtureLocaliser,
    Localisation,
    POState,
    birth_mixture,
    sensor_measurement,
)

__all__ = [
    "FlowMixtureLocaliser",
    "BootstrapLocaliser",
    "POState",
    "Localisation",
    "birth_mixture",
    "sensor_measurement",
    "METHODS",
    "Association",
    "loopy_association",
]
