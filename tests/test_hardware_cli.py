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


def test_serve_twin_needs_an_indenter_and_streams_the_twin(tmp_path) -> None:
    ports = ["--rws-port", "0", "--kms40-port", "0", "--egm-ports", "0,0", "--biotac-port", "0"]
    twin = ["--twin", "--quick", "--sensors", "1", "--mesh-mm", "3"]
    result = runner.invoke(app, ["devices", "serve", *ports, *twin, "--duration-s", "0.1"])
    assert result.exit_code == 2 and "--indenter" in result.output
    result = runner.invoke(app, ["devices", "serve", *ports, "--indenter", "sphere_small", "--duration-s", "0.1"])
    assert result.exit_code == 2 and "add --twin" in _text(result.output)
    result = runner.invoke(app, ["devices", "serve", *ports, *twin, "--indenter", "cone", "--duration-s", "0.1"])
    assert result.exit_code == 2 and "not indented with 'cone'" in result.output  # sensor 1: spheres only
    out = tmp_path / "sim.toml"
    args = [*ports, *twin, "--indenter", "sphere_small", "--config-out", str(out), "--duration-s", "0.3"]
    result = runner.invoke(app, ["devices", "serve", *args])
    assert result.exit_code == 0, result.output
    config = load_config(out)
    assert config.kms40.port != 0 and config.egm.watchdog_s == config.biotac.watchdog_s == 0.5
    assert "twin: 0 contact solves" in result.output and "0 failed" in result.output


def test_campaign_run_on_hardware_refuses_what_one_robot_cannot_do(tmp_path) -> None:
    config = tmp_path / "hw.toml"
    config.write_text(config_to_toml(HardwareConfig()))
    base = ["campaign", "run", "--out", str(tmp_path / "out"), "--quick"]
    hardware = [*base, "--backend", "hardware", "--config", str(config)]
    cases = {
        "needs --config FILE": [*base, "--backend", "hardware"],
        "it needs --backend hardware": [*base, "--config", str(config)],
        "one robot, one trajectory at a time": [*hardware, "--workers", "2"],
        "one mounted sensor": [*hardware, "--sensors", "1,2"],
        "sim or hardware": [*base, "--backend", "robot"],
    }
    for message, args in cases.items():
        result = runner.invoke(app, args)
        assert result.exit_code == 2 and message in _text(result.output), (message, result.output)
    config.write_text("[kms40]\nprot = 1000\n")
    result = runner.invoke(app, [*hardware, "--sensors", "1"])
    assert result.exit_code == 2 and "unknown key(s) in" in result.output and "prot" in result.output


def test_campaign_run_on_hardware_says_which_device_does_not_answer(tmp_path) -> None:
    with SimulatedTestbed(rws_port=0, kms40_port=0, egm_ports=(0, 0), biotac_port=0) as testbed:
        dead = with_changes(testbed.hardware_config(), kms40={"timeout_s": 0.2})
    config = tmp_path / "hw.toml"
    config.write_text(config_to_toml(dead))
    args = ["--quick", "--sensors", "1", "--indenters", "sphere_small", "--mesh-mm", "3", "--yes"]
    result = runner.invoke(
        app,
        ["campaign", "run", "--out", str(tmp_path / "out"), "--backend", "hardware", "--config", str(config), *args],
    )
    assert result.exit_code == 1
    assert "cannot open the hardware backend" in _text(result.output)
    assert not (tmp_path / "out" / "biotac1.hdf5").exists()


def _text(output: str) -> str:
    """CLI output without rich's box drawing and line wrapping."""
    return " ".join(output.translate({ord(c): " " for c in "│╭╮╰╯─"}).split())
