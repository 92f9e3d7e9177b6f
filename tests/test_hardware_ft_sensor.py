"""The F/T-sensor seam: a new sensor family is one config section, and the backend then reads, watches and
stops on it alone (the KMS40 is not even running); `[ft] sensor` must name an F/T section."""

import json
import threading
from collections import Counter
from dataclasses import dataclass, field, fields, make_dataclass

import numpy as np
import pytest

from hardware.backend import HardwareBackend
from hardware.config import FtConfig, HardwareConfig, load_config, with_changes
from hardware.ft_sensor import FtSensorConfig
from hardware.kms40.config import Kms40Config
from hardware.stamped import Latest
from hardware.testbed import REST_WRENCH, SimulatedTestbed
from twin.backend import BackendError

SCRIPTED = (1.0, -2.0, -3.0, 0.01, 0.02, 0.03)  # N, N·m: unlike the KMS40 simulator's rest wrench


class ScriptedSensor:
    """A stand-in F/T sensor family: streams `load` (N, N·m) every 4 ms from a thread until closed."""

    def __init__(self, load: tuple[float, ...]) -> None:
        self.load = np.array(load)
        self.wrench: Latest[np.ndarray] = Latest("scripted F/T")
        self.stats: Counter[str] = Counter()
        self.info: dict[str, object] = {"serial": "SCRIPT-1"}
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._stream, daemon=True)
        self._thread.start()

    def _stream(self) -> None:
        while not self.closed.wait(0.004):
            self.wrench.put(self.load.copy())
            self.stats["frames"] += 1

    def close(self) -> None:
        self.closed.set()
        self._thread.join(timeout=1.0)


OPENED: list[ScriptedSensor] = []


@dataclass(frozen=True)
class ScriptedConfig:
    """The new family's config section: defaults for everything, timeout_s, watchdog_s and open()."""

    load: tuple[float, ...] = SCRIPTED
    timeout_s: float = 1.0
    watchdog_s: float = 0.5

    def open(self) -> ScriptedSensor:
        OPENED.append(ScriptedSensor(self.load))
        return OPENED[-1]


# the one config entry: a field of HardwareConfig naming the section (a subclass here, to leave hardware/ alone)
BenchConfig = make_dataclass(
    "BenchConfig",
    [("scripted", ScriptedConfig, field(default_factory=ScriptedConfig))],
    bases=(HardwareConfig,),
    frozen=True,
)


def test_a_new_ft_sensor_is_one_config_section_and_the_backend_uses_only_it() -> None:
    with SimulatedTestbed(rws_port=0, kms40_port=0, egm_ports=(0, 0), biotac_port=0) as testbed:
        base = with_changes(
            testbed.hardware_config(watchdog_s=0.5),
            egm={"startup_timeout_s": 2.0},
            safety={"force_limit_n": 3.0, "retract_timeout_s": 2.0},
        )
        testbed.kms40.close()  # the KMS40 is gone: opening it would fail
        sections = {f.name: getattr(base, f.name) for f in fields(base)}
        config = BenchConfig(**{**sections, "ft": FtConfig("scripted")})
        assert isinstance(config.ft_sensor, FtSensorConfig) and config.ft_sensor is config.scripted
        backend = HardwareBackend(config)
        try:
            sensor = OPENED[-1]
            sample = backend.read()
            np.testing.assert_array_equal(sample.wrench, SCRIPTED)
            assert not np.allclose(sample.wrench, REST_WRENCH)
            status = backend.status()
            assert status["scripted_info"] == {"serial": "SCRIPT-1"} and status["scripted"]["frames"] > 0
            assert "kms40" not in status
            backend.advance(0.05)  # steady load: no trip
            sensor.load = sensor.load + np.array([0.0, 0.0, -5.0, 0.0, 0.0, 0.0])  # 5 N more than at opening
            with pytest.raises(BackendError, match=r"force limit 3 N exceeded \(\|dF\| = 5.00 N\)"):
                backend.advance(0.2)
        finally:
            backend.close()
        assert sensor.closed.is_set()
        with pytest.raises(BackendError, match="cannot open the hardware backend: KMS40: cannot connect"):
            HardwareBackend(with_changes(base, kms40={"timeout_s": 0.2}))


def test_ft_sensor_names_an_ft_section(tmp_path) -> None:
    assert HardwareConfig().ft.sensor == "kms40" and HardwareConfig().ft_sensor == Kms40Config()
    assert isinstance(Kms40Config(), FtSensorConfig)
    for name in ("egm", "biotac", "ati"):
        with pytest.raises(ValueError, match=rf"ft.sensor must name an F/T sensor section \(kms40\), got '{name}'"):
            with_changes(HardwareConfig(), ft={"sensor": name})
    path = tmp_path / "hw.json"
    path.write_text(json.dumps({"ft": {"sensor": "kms40"}, "kms40": {"port": 1001}}))
    assert load_config(path).ft_sensor.port == 1001
    path.write_text(json.dumps({"ft": {"sensor": "rws"}}))
    with pytest.raises(ValueError, match="ft.sensor must name"):
        load_config(path)
