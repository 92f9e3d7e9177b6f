"""Hardware configuration: where the devices are and how carefully to drive them, from TOML or JSON.

Every field has the real testbed's default (factory addresses and ports from the facts); a file only
needs what differs. Unknown sections or keys are errors, so a typo cannot silently fall back to a
default. Times in seconds, forces in N, angles in rad, speeds in rad/s.
"""

from __future__ import annotations

import json
import re
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from hardware.ft_sensor import FtSensorConfig
from hardware.kms40.config import Kms40Config

TRANSPORT_SPEC = re.compile(r"cheetah(:\d+)?|tcp://[^:/\s]+:\d+")
AUTO_BIND = "auto"


@dataclass(frozen=True)
class RwsConfig:
    """Robot Web Services 1.0 of the YuMi's IRC5 controller."""

    host: str = "192.168.125.1"
    port: int = 80
    user: str = "Default User"
    password: str = "robotics"
    timeout_s: float = 5.0
    start_rapid: bool = True
    """Start RAPID (whose program runs EGMRunJoint on both tasks) when the backend opens."""
    stop_rapid_on_close: bool = True


@dataclass(frozen=True)
class EgmConfig:
    """EGM joint streaming: this PC listens on one UDP port per arm and hears only the controller."""

    bind_host: str = AUTO_BIND
    """Address of this PC to listen on; "auto": the interface that routes to `robot_host` (never all)."""
    left_port: int = 6511
    right_port: int = 6512
    robot_host: str = "192.168.125.1"
    """The controller: EgmRobot from any other address is dropped, counted (`foreign`), never answered."""
    left_robot_port: int = 0
    right_robot_port: int = 0
    """UDP port each arm's EGM comes from (the UDPUC device's local port); 0: any port of `robot_host`."""
    startup_timeout_s: float = 10.0
    """How long to wait for the first EgmRobot of each arm after RAPID starts."""
    watchdog_s: float = 0.1
    """Feedback older than this (25 EGM cycles) is a fault."""
    max_speed: float = 0.5
    """Joint speed (rad/s) at which commanded targets are approached; far below YuMi's limits."""


@dataclass(frozen=True)
class FtConfig:
    """Which F/T sensor the backend opens: the name of its config section (e.g. "kms40")."""

    sensor: str = "kms40"


@dataclass(frozen=True)
class BioTacConfig:
    """BioTac behind an SPI adapter: "cheetah", "cheetah:PORT", or "tcp://HOST:PORT" (SPI bridge)."""

    transport: str = "cheetah"
    select_mask: int = 0x01
    """The one sensor the backend reads: 0x01, 0x02 or 0x04 (adapter slot 1, 2 or 3)."""
    bitrate_khz: int = 4400
    reconnect_s: float = 0.5
    watchdog_s: float = 0.1
    """Frames arrive at 100 Hz; older than this is a fault."""


@dataclass(frozen=True)
class SafetyConfig:
    """Limits the backend enforces on its own, below whatever the controller does."""

    force_limit_n: float = 30.0
    """|F| change since the backend opened (N) that stops the arms and retracts."""
    free_force_n: float = 0.5
    """Below this |F| change (N) a pose counts as contact-free (a safe place to retract to)."""
    retract_timeout_s: float = 10.0
    poll_s: float = 0.004
    """How often advance() checks force and watchdogs while time passes."""


@dataclass(frozen=True)
class HardwareConfig:
    """Everything `HardwareBackend` needs; sections as in the TOML file ([rws], [egm], ...)."""

    rws: RwsConfig = field(default_factory=RwsConfig)
    egm: EgmConfig = field(default_factory=EgmConfig)
    ft: FtConfig = field(default_factory=FtConfig)
    kms40: Kms40Config = field(default_factory=Kms40Config)
    biotac: BioTacConfig = field(default_factory=BioTacConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)

    def __post_init__(self) -> None:
        if not TRANSPORT_SPEC.fullmatch(self.biotac.transport):
            raise ValueError(
                f"biotac.transport must be cheetah, cheetah:PORT or tcp://HOST:PORT, got {self.biotac.transport!r}"
            )
        if self.biotac.select_mask not in (0x01, 0x02, 0x04):
            raise ValueError(f"biotac.select_mask must be 0x01, 0x02 or 0x04, got {self.biotac.select_mask:#x}")
        for name, port in (
            ("rws.port", self.rws.port),
            ("egm.left_port", self.egm.left_port),
            ("egm.right_port", self.egm.right_port),
            ("egm.left_robot_port", self.egm.left_robot_port),
            ("egm.right_robot_port", self.egm.right_robot_port),
        ):
            if not 0 <= port <= 65535:
                raise ValueError(f"{name} must be a port number 0..65535, got {port}")
        if not 0 < self.safety.free_force_n < self.safety.force_limit_n:
            raise ValueError("need 0 < safety.free_force_n < safety.force_limit_n")
        sensors = [f.name for f in fields(self) if isinstance(getattr(self, f.name), FtSensorConfig)]
        if self.ft.sensor not in sensors:
            raise ValueError(
                f"ft.sensor must name an F/T sensor section ({', '.join(sensors)}), got {self.ft.sensor!r}"
            )

    @property
    def ft_sensor(self) -> FtSensorConfig:
        """The config section of the F/T sensor the backend opens (`[ft] sensor`)."""
        return getattr(self, self.ft.sensor)


def config_from_dict(data: dict[str, Any]) -> HardwareConfig:
    """Build a HardwareConfig from nested sections; ValueError on unknown sections/keys or wrong types."""
    sections = {}
    for section in fields(HardwareConfig):
        values = dict(data.get(section.name, {}))
        cls = section.default_factory
        known = {f.name: f for f in fields(cls)}
        unknown = set(values) - set(known)
        if unknown:
            raise ValueError(f"unknown key(s) in [{section.name}]: {', '.join(sorted(unknown))}")
        for key, value in values.items():
            expected = type(getattr(cls(), key))
            if expected is float and isinstance(value, int) and not isinstance(value, bool):
                values[key] = float(value)
            elif not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
                raise ValueError(f"[{section.name}] {key} must be {expected.__name__}, got {value!r}")
        sections[section.name] = cls(**values)
    unknown = set(data) - set(sections)
    if unknown:
        raise ValueError(f"unknown section(s): {', '.join(sorted(unknown))}")
    return HardwareConfig(**sections)


def load_config(path: str | Path) -> HardwareConfig:
    """Read a `.toml` or `.json` hardware config file."""
    path = Path(path)
    if path.suffix not in (".toml", ".json"):
        raise ValueError(f"hardware config must be .toml or .json, got {path.name}")
    text = path.read_text()
    data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    return config_from_dict(data)


def config_to_toml(config: HardwareConfig) -> str:
    """The config as TOML text that `load_config` reads back to an equal config."""
    lines = []
    for section, values in asdict(config).items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in values.items()]
        lines.append("")
    return "\n".join(lines)


def with_changes(config: HardwareConfig, **sections: dict[str, Any]) -> HardwareConfig:
    """A copy of `config` with some fields of some sections replaced, e.g. rws={"port": 8080}."""
    return replace(config, **{name: replace(getattr(config, name), **values) for name, values in sections.items()})
