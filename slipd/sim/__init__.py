"""Ground truth: scenarios on an independent plant (CommonRoad's multi-body model) -> the CAN
messages a real car would send, and the true sideslip.

``simulate(scenario, vehicle=2, seed=0, duration=None) -> SimResult`` is the programmatic entry;
``SCENARIOS`` names every scenario with the paper it mirrors. The simulator imports nothing from
slipd.estimators: the truth is independent of the methods it judges.
"""

from slipd.sim.core import simulate
from slipd.sim.result import MessageSamples, MessageSpec, SimResult
from slipd.sim.scenarios import SCENARIOS, Scenario

__all__ = ["SCENARIOS", "MessageSamples", "MessageSpec", "Scenario", "SimResult", "simulate"]
