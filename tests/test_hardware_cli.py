"""`twin devices serve|check|config`: configs that load back, a preflight over simulated devices, clean errors."""

import json

from typer.testing import CliRunner

from hardware.config import HardwareConfig, config_to_toml, load_config, with_changes
from hardware.testbed import REST_ELECTRODES, SimulatedTestbed
from twin.cli import app

runner = CliRunner()


def test_config_template_is_the_factory_config(tmp_path) -> None:
    result = runner.invoke(app, ["devices", "config"])
    assert result.exit_code == 0, result.output
    path = tmp_path / "hw.toml"
    path.write_text(result.stdout)
    assert load_config(path) == HardwareConfig()


def test_serve_writes_a_config_that_points_at_its_devices(tmp_path) -> None:
    out = tmp_path / "sim.toml"
    args = ["devices", "serve", "--rws-port", "0", "--kms40-port", "0", "--egm-ports", "0,0", "--biotac-port", "0"]
    result = runner.invoke(app, [*args, "--config-out", str(out), "--duration-s", "0.2"])
    assert result.exit_code == 0, result.output
    config = load_config(out)
    assert config.rws.host == config.kms40.host == "127.0.0.1"
    assert 0 not in (config.rws.port, config.kms40.port, config.egm.left_port, config.egm.right_port)
    assert config.biotac.transport.startswith("tcp://127.0.0.1:")
    bad = runner.invoke(app, ["devices", "serve", "--egm-ports", "6511"])
    assert bad.exit_code == 2 and "left,right" in " ".join(bad.output.split())


def test_check_reads_every_device_and_reports_failures(tmp_path) -> None:
    path = tmp_path / "hw.toml"
    with SimulatedTestbed(rws_port=0, kms40_port=0, egm_ports=(0, 0), biotac_port=0) as testbed:
        wide = {"watchdog_s": 0.5}  # tests share busy cores
        path.write_text(config_to_toml(with_changes(testbed.hardware_config(), egm=wide, kms40=wide, biotac=wide)))
        result = runner.invoke(app, ["devices", "check", str(path), "--json"])
        assert result.exit_code == 0, result.output
        report = json.loads(result.stdout.strip().splitlines()[-1])
        assert report["electrodes"] == REST_ELECTRODES.astype(int).tolist()
        assert report["joints_deg"]["left"] == [0.0] * 7
        assert report["egm"]["left"]["received"] > 0
        assert not testbed.rws.rapid_running  # check stops what it started
        dead = with_changes(testbed.hardware_config(), kms40={"port": testbed.kms40.port, "timeout_s": 0.2})
    path.write_text(config_to_toml(dead))
    result = runner.invoke(app, ["devices", "check", str(path)])
    assert result.exit_code == 1 and "cannot connect" in " ".join(result.output.split())  # rich wraps lines
