"""Robot Web Services 1.0 facts that the client and the simulated controller share.

Resource names of YuMi's mechanical units, the form that starts RAPID, the Digest
realm and session cookie of an IRC5, and the joint target's fields: degrees, `rax_1`..`rax_6` for
ABB axes 1-6 and `eax_a` for YuMi's axis 7 (the first external axis).
"""

from __future__ import annotations

import numpy as np

START_FORM = {
    "regain": "continue",
    "execmode": "continue",
    "cycle": "once",
    "condition": "none",
    "stopatbp": "disabled",
    "alltaskbytsp": "true",
}
"""POST body of rw/rapid/execution?action=start: run every task once from where it stands."""
MECHUNITS = {"left": "ROB_L", "right": "ROB_R"}
REALM = "validusers@robapi.abb"
SESSION_COOKIE = "-http-session-"
JOINT_KEYS = ("rax_1", "rax_2", "eax_a", "rax_3", "rax_4", "rax_5", "rax_6")
"""The jointtarget fields in chain order 1-2-7-3-4-5-6 (degrees)."""


def jointtarget_to_chain(state: dict[str, str]) -> np.ndarray:
    """(7,) joints (rad, chain order) of a jointtarget reply; KeyError or ValueError if it has none."""
    return np.radians([float(state[key]) for key in JOINT_KEYS])


def chain_to_jointtarget(q_rad: np.ndarray) -> dict[str, str]:
    """The jointtarget fields (degrees, 6 decimals) of (7,) joints in rad, chain order."""
    return dict(zip(JOINT_KEYS, (f"{d:.6f}" for d in np.degrees(q_rad)), strict=True))
