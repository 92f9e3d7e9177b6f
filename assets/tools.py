"""Tools mounted on a YuMi flange: the nine indenters and the registration pin.

Frames (metres): the ``flange`` frame is the YuMi flange of ``twin.kinematics`` (z out of the flange).
Every tool's ``tip`` frame follows the indenter frame of ``assets.indenters``: origin at the tip, the
tool body along +z (toward the flange), the tool presses along -z. A tool therefore sits on the flange
turned half a turn about x: tip z = -flange z, tip x = flange x.

Indenters: each public indenter mesh is 17.86 mm from tip to shank end (``TOTAL_LENGTH``); the shank
end sits on the flange face, so the tip is ``TOTAL_LENGTH + adapter_length`` out along the flange z.

Registration pin (``PIN``): a shoulder pin (paper, Methods B). Its tip frame is on the pin axis at the
shoulder face, the point that rests on a hole liner's rim when the pin is seated; the nose below the
shoulder enters the liner. Dimensions are design choices, not measured (docs/testbed.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets.indenters import INDENTERS, TOTAL_LENGTH

PIN = "pin"
"""Tool name of the registration pin."""


@dataclass(frozen=True)
class PinGeometry:
    """Shoulder pin, metres. shaft: flange face to shoulder; nose: below the shoulder, into the liner."""

    shaft_length: float = 50e-3
    shaft_radius: float = 5e-3
    nose_length: float = 8e-3
    nose_radius: float = 3e-3


DEFAULT_PIN = PinGeometry()
TOOLS: tuple[str, ...] = (*INDENTERS, PIN)
"""Every tool name accepted here: the nine indenters, then the pin."""


def _check_tool(tool: str) -> str:
    if tool not in TOOLS:
        raise ValueError(f"unknown tool {tool!r}; valid tools: {', '.join(TOOLS)}")
    return tool


def tool_length(tool: str, adapter_length: float = 0.0, pin: PinGeometry = DEFAULT_PIN) -> float:
    """Distance (m) from the flange face to the tool's tip frame along the flange z axis."""
    base = pin.shaft_length if _check_tool(tool) == PIN else TOTAL_LENGTH
    return base + adapter_length


def tool_tip_transform(tool: str, adapter_length: float = 0.0, pin: PinGeometry = DEFAULT_PIN) -> np.ndarray:
    """(4, 4) flange -> tip transform of `tool` (p_flange = T @ p_tip), m.

    adapter_length: extra spacer (m) between the flange face and the tool's mounting end.
    """
    t = np.diag([1.0, -1.0, -1.0, 1.0])
    t[2, 3] = tool_length(tool, adapter_length, pin)
    return t
