"""Test-wide settings: the simulated camera renders small frames so the suite stays fast on two cores."""

import os

os.environ.setdefault("MCA_SIM_SIZE", "small")
os.environ.setdefault("RERUN_ANALYTICS", "0")
