"""Test-wide settings: the simulated camera renders small frames so the suite stays fast on two cores, and
Ctrl-C can be delivered even when the suite itself was started with SIGINT ignored."""

import os
import signal

os.environ.setdefault("MCA_SIM_SIZE", "small")
os.environ.setdefault("RERUN_ANALYTICS", "0")

# A background job of a non-interactive shell (`cmd &`, many CI runners, nohup) starts with SIGINT ignored;
# Python then never installs its KeyboardInterrupt handler, and children inherit the ignored signal. The
# tests that press Ctrl-C (test_tether_interrupts, the fault suite, test_safety_inputs) would wait forever.
# A handler set here is reset to the default in every child at exec, so children get Ctrl-C back too.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
