"""The plant: the simulated "real world" that simulated measurements come from.

A plant is the nominal model plus per-sensor variability (three BioTacs that differ), mount
placement error, F/T bias and sensor noise. Predictions never come from a plant: the model side only
sees the nominal parameters, so whatever the plant hides stays hidden (DESIGN.md).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from fe.electrodes import ElectrodeParameters
from fe.params import SkinParameters
from twin.backend import ARMS
from twin.effects import EffectValues, check_values
from twin.kinematics import rotation_exp
from twin.registration import ENCODER_NOISE_RAD, PAPER_JOINT_OFFSET_STD


@dataclass(frozen=True)
class MeasurementNoise:
    """Standard deviations of the sensor noise (SI units)."""

    force: float = 0.01
    """KMS40 force noise per axis (N)."""
    torque: float = 2e-4
    """KMS40 torque noise per axis (N·m)."""
    encoder: float = 2e-5
    """YuMi joint-encoder noise (rad); 2e-5 rad at 0.5 m reach is 0.01 mm."""
    ft_bias_force: float = 0.5
    """Spread of the per-sensor F/T force bias (N); removed by taring."""
    ft_bias_torque: float = 0.02
    """Spread of the per-sensor F/T torque bias (N·m)."""


@dataclass(frozen=True)
class PlantSensor:
    """One physical BioTac as the plant knows it (SI units).

    mount_error: (6,) true mount placement error of this sensor: rotation vector (rad) then
    translation (m), applied in the robot frame to the scene's nominal robot->biotac transform.
    ft_bias: (6,) untared F/T offset (N, N·m).
    """

    sensor_id: int
    skin: SkinParameters
    electrodes: ElectrodeParameters
    mount_error: np.ndarray
    ft_bias: np.ndarray


@dataclass(frozen=True)
class Plant:
    """Per-sensor truth plus noise and hidden effects; `seed` drives every random draw made while measuring.

    effects: effect values (twin.effects) the real world has and the nominal model lacks.
    registration_clearance: pin-liner clearance (m) of the simulated registration (0: exact).
    registration_encoder_noise: joint-reading noise (rad) during registration (0: exact).
    """

    sensors: dict[int, PlantSensor]
    noise: MeasurementNoise = field(default_factory=MeasurementNoise)
    seed: int = 0
    effects: EffectValues = field(default_factory=dict)
    registration_clearance: float = 0.3e-3
    registration_encoder_noise: float = ENCODER_NOISE_RAD
    joint_offsets: dict[str, np.ndarray] = field(default_factory=dict)
    """arm -> (7,) real joint zero offsets (rad): the arm's true shape is the nominal model at reading + offset."""

    def joint_offset(self, arm: str) -> np.ndarray:
        """(7,) joint zero offsets of `arm` (zeros when the plant has none)."""
        return np.asarray(self.joint_offsets.get(arm, np.zeros(7)), dtype=float)

    def __post_init__(self) -> None:
        check_values(self.effects)

    def sensor(self, sensor_id: int) -> PlantSensor:
        """The plant's sensor `sensor_id`, or a ValueError naming the ones it has."""
        if sensor_id not in self.sensors:
            raise ValueError(f"the plant has no sensor {sensor_id}; it has {sorted(self.sensors)}")
        return self.sensors[sensor_id]

    def fingerprint(self) -> str:
        """A short hash of everything the plant is made of (recorded instead of the values themselves)."""
        text = json.dumps(_jsonable(asdict(self)), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _jsonable(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def make_plant(
    sensor_ids: list[int],
    seed: int,
    nominal: SkinParameters = SkinParameters(),
    variability: float = 0.05,
    noise: MeasurementNoise = MeasurementNoise(),
    mount_rotation_error: float = 2e-3,
    mount_translation_error: float = 0.5e-3,
    effects: EffectValues | None = None,
    exact_registration: bool = False,
    joint_offset_std: float = PAPER_JOINT_OFFSET_STD,
) -> Plant:
    """Draw a plant of sensors that differ from `nominal` by `variability` (relative, 1 sigma).

    Skin thickness and modulus vary by `variability`, friction by twice that; electrodes get their
    own gains and offsets; each mount is placed with errors of the given sizes (rad, m, 1 sigma).
    `effects` are hidden in the plant; each arm's joints have zero offsets of RMS `joint_offset_std`
    (rad; `joint_offsets`); `exact_registration` removes registration noise and joint offsets.
    """
    if not sensor_ids or len(set(sensor_ids)) != len(sensor_ids) or min(sensor_ids) < 1:
        raise ValueError(f"sensor ids must be distinct positive integers, got {sensor_ids!r}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E45]))
    sensors = {}
    for sid in sensor_ids:
        factor = np.exp(variability * rng.standard_normal(3) * np.array([1.0, 1.0, 2.0]))
        skin = replace(
            nominal,
            thickness=nominal.thickness * factor[0],
            mu_nh=nominal.mu_nh * factor[1],
            friction=nominal.friction * factor[2],
        )
        mount_error = np.concatenate(
            [mount_rotation_error * rng.standard_normal(3), mount_translation_error * rng.standard_normal(3)]
        )
        bias = np.concatenate(
            [noise.ft_bias_force * rng.standard_normal(3), noise.ft_bias_torque * rng.standard_normal(3)]
        )
        sensors[sid] = PlantSensor(sid, skin, ElectrodeParameters.sample(rng), mount_error, bias)
    if exact_registration:
        return Plant(sensors, noise, seed, dict(effects or {}), 0.0, 0.0)
    offsets = {arm: joint_offsets(rng, joint_offset_std) for arm in ARMS}
    return Plant(sensors, noise, seed, dict(effects or {}), joint_offsets=offsets)


def joint_offsets(rng: np.random.Generator, rms: float) -> np.ndarray:
    """(7,) joint zero offsets (rad) of RMS exactly `rms`, in a direction drawn uniformly.

    An arm's calibration error has a known size and an unknown direction. At `PAPER_JOINT_OFFSET_STD`
    the registration error it causes has its median in the paper's 0.5-1.5 mm band (0.68-0.86 mm over
    24-40 seeds and both arms) with 63-69 % of draws inside it; independent Gaussian offsets of that
    spread add their chi spread of sizes and put 54-59 % inside (tests/test_registration.py).
    """
    direction = rng.standard_normal(7)
    return rms * np.sqrt(7.0) * direction / np.linalg.norm(direction)


def rigid_transform(rotation_vector: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 transform from a rotation vector (rad, axis * angle) and a translation (m)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_exp(rotation_vector)
    pose[:3, 3] = translation
    return pose
