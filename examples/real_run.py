# %% [markdown]
# # slipd from Python: the Ferrari 250 LM run, three estimators, one figure
#
# A notebook as a plain script (run it with `python examples/real_run.py [OUT_DIR]`, or open
# it in VS Code / Jupytext: each `# %%` is a cell). It imports the real recorded run of
# `../shared/realdata/revs_250lm` onto slipd's bus exactly as README "Bring your own recorded
# data" does, decodes it, runs three estimators, scores them against the INS truth and draws
# them. CI runs it (tests/test_examples.py).

# %%
import sys
from pathlib import Path

import slipd

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "realdata" / "revs_250lm" / "revs_250lm.csv"
PROFILE = ROOT / "examples" / "revs_250lm" / "ferrari_250lm.toml"
OUT = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "runs" / "examples"
OUT.mkdir(parents=True, exist_ok=True)
LOG = OUT / "revs_250lm.log"

# %% [markdown]
# ## 1. The recording onto the bus (README step 4: `slipd import`)
# The INS signals become slipd.dbc frames through the codec (counters, CRCs, quantisation);
# the wheel speeds are derived from the INS speed with zero sideslip, as the recipe says, and
# the INS sideslip goes to the truth CSV beside the log.

# %%
from slipd.profile import load_profile
from slipd.replay.importer import import_table, parse_map, parse_truth

profile = load_profile(PROFILE)
report = import_table(
    DATA, profile,
    parse_map(["ax_cog_mps2=ax,ay_cog_mps2=ay,yaw_rate_radps=yaw_rate,steer_road_rad=steer"]),
    LOG, time_spec="t_s:s", derive=["wheel-speeds"], speed_spec="vx_mps:m/s",
    truth=parse_truth(["beta=beta_rad,vx=vx_mps,vy=vy_mps,yaw_rate=yaw_rate_radps"]))
print(report.summary())

# %% [markdown]
# ## 2. What the estimators see: SI channels per 10 ms tick, with validity

# %%
inputs = slipd.decode(LOG, profile=profile)
print(inputs[["t", "ay", "yaw_rate", "steer", "wheel_speed_fl", "ay_valid"]].describe())

# %% [markdown]
# ## 3. Three methods over the whole run, and their scores against the INS truth
# The default `d_ekf` (Righetti & Lenzo 2025's dynamic EKF), `kinematic_heuristic`
# (Selmanaj et al. 2017) and `zero`, the floor. The scores include how often each was
# VALID and how often a VALID tick was more than 5 deg off.

# %%
methods = ["d_ekf", "kinematic_heuristic", "zero"]
estimates = slipd.estimate(LOG, profile=profile, estimator=methods)
truth = slipd.read_truth(LOG.with_name("revs_250lm.truth.csv"))
scores = slipd.evaluate(estimates, truth)
print(scores[["beta_rms_deg", "beta_p99_deg", "valid_fraction", "valid_err_over_5deg",
              "sigma2_coverage"]].round(3).to_string())

# %% [markdown]
# ## 4. The figure: inputs, beta where VALID, VALID spans, error over time, error CDF

# %%
figure = slipd.plot(estimates, truth, OUT / "revs_250lm.png", inputs=inputs,
                    title="Ferrari 250 LM, Stanford Revs (real run)")
print(f"figure -> {OUT / 'revs_250lm.png'}")

# %% [markdown]
# ## 5. The same estimator tick by tick, as you would embed it in your own loop
# `slipd.Estimator.step` takes one tick of SI values (a decoded row here); its outputs are
# the batch run's exactly.

# %%
import numpy as np

embedded = slipd.Estimator("d_ekf", profile=profile)
first_minute = inputs.iloc[:6000]
stepped = np.array([embedded.step(row).beta for row in first_minute.to_dict("records")])
batch = estimates.loc[estimates["estimator"] == "d_ekf", "beta"].to_numpy()[:6000]
print(f"Estimator.step vs estimate over the first minute: max |difference| = "
      f"{np.max(np.abs(stepped - batch)):.3g} rad")
assert np.array_equal(stepped, batch)
