"""``pseudo_fusion_dbe``: the DBE of Chen et al. 2018 alone (``pseudo_fusion`` with PART = DBE).

The same kernel and state as ``pseudo_fusion`` (see ``slipd.estimators.chen``); only the
output differs, so it is exactly the part that enters the fusion.
"""

from __future__ import annotations

from slipd.estimators.chen import DEFAULTS as _CHEN_DEFAULTS
from slipd.estimators.chen import PARAMS, Part, S, init, run_ticks, step

__all__ = ["DEFAULTS", "PARAMS", "S", "init", "run_ticks", "step"]

DEFAULTS = {**_CHEN_DEFAULTS, "part": float(Part.DBE)}
