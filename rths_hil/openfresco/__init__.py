"""OpenSees (or OpenFresco) drives the bridge: an OpenFresco-compatible experimental site.

:mod:`.protocol` the wire format, :mod:`.server` the TCP server, :mod:`.timing` the timing
modes (lockstep, predictor–corrector, ramp-hold), :mod:`.site` the mapping and the structure
stage the loop drives. See docs/opensees.md.
"""

from .site import DEFAULTS, TIMINGS, ExperimentalSite, Mapping, SiteFault

__all__ = ["DEFAULTS", "TIMINGS", "ExperimentalSite", "Mapping", "SiteFault"]
