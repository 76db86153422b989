"""Default signal names of the default inverter (contract, DESIGN.md "Signals").

The one home of these names: the plant simulates them, readers fall back to
them when a file carries no sidecar. Other inverters use other names through
configuration.
"""
STATE_NAMES = (
    "delta", "Pf", "Qf", "phi_d", "phi_q", "gamma_d", "gamma_q",
    "il_d", "il_q", "vc_d", "vc_q", "ig_d", "ig_q",
)
INPUT_NAMES = ("ug", "theta_g")
#: channels over which the paper's error metric ε is averaged
SCORED_STATES = ("ig_d", "ig_q", "vc_d", "vc_q")
SAMPLE_RATE_HZ = 10_000.0
