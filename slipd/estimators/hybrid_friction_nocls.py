"""``hybrid_friction_nocls``: the adaptive state observer of Carnier, Corno, Savaresi 2023
(Sec. 2) without the friction classifier of Sec. 3 - the "pure adaptive observer" the paper
compares against in Fig. 13, 15 and 16.

The same kernel as ``hybrid_friction`` with ``classifier_enabled = 0``: mu hat starts at
MU_NOMINAL (the paper initialises on dry asphalt) and adapts only through eq. 14-15. See
``slipd.estimators.hybrid_friction`` for everything else.
"""

from __future__ import annotations

from slipd.estimators import hybrid_friction as _full

PARAMS = _full.PARAMS
DEFAULTS = {**_full.DEFAULTS, "classifier_enabled": 0.0}
init = _full.init
step = _full.step
run_ticks = _full.run_ticks
