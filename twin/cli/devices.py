"""`twin devices ...`: simulated YuMi (EGM + RWS), KMS40 and BioTac devices on loopback, and preflight checks."""

from __future__ import annotations

import ipaddress
import json
import socket
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape

from twin.cli.common import MeshMm, Quick, Seed, Sensors, campaign_config, err_console, guarded

if TYPE_CHECKING:
    from twin.loopback_rig import TwinSources

devices_app = typer.Typer(help="Simulated devices that speak the real wire protocols.", no_args_is_help=True)


def _ports(text: str) -> tuple[int, int]:
    try:
        left, right = (int(p) for p in text.split(","))
    except ValueError as exc:
        raise typer.BadParameter(
            f"--egm-ports needs two comma-separated port numbers (left,right), got {text!r}"
        ) from exc
    return left, right


def exposure_warning(host: str) -> str | None:
    """What serving on `host` exposes beyond this machine (None for a loopback address)."""
    if host in ("0.0.0.0", ""):
        where = "all interfaces (0.0.0.0)"
    else:
        try:
            if ipaddress.ip_address(socket.gethostbyname(host)).is_loopback:
                return None
        except (OSError, ValueError):
            return None  # not an address of this machine: opening the ports will say so
        where = host
    return (
        f"WARNING: serving on {where}: anyone who reaches this machine can log in to the simulated RWS "
        "with the factory password ('Default User' / 'robotics') and start RAPID; the KMS40 and the BioTac "
        "SPI bridge take no password at all. Use this only on a network you trust."
    )


@devices_app.command("serve")
def serve(
    host: Annotated[
        str, typer.Option(help="Address to serve on (loopback by default; others expose the factory password).")
    ] = "127.0.0.1",
    rws_port: Annotated[int, typer.Option(help="RWS HTTP port (real: 80; 0 = any free port).")] = 80,
    kms40_port: Annotated[int, typer.Option(help="KMS40 TCP port (real: 1000; 0 = any free port).")] = 1000,
    egm_ports: Annotated[
        str, typer.Option(help="UDP ports the arms send EGM to, left,right (0 = free).")
    ] = "6511,6512",
    biotac_port: Annotated[int, typer.Option(help="TCP port of the BioTac SPI bridge (0 = any free port).")] = 6540,
    egm_loss: Annotated[float, typer.Option(help="Fraction of EGM datagrams to drop (0..1).")] = 0.0,
    egm_delay_ms: Annotated[float, typer.Option(help="Extra EGM latency each way (ms).")] = 0.0,
    config_out: Annotated[Path | None, typer.Option(help="Also write the matching hardware config here.")] = None,
    duration_s: Annotated[float | None, typer.Option(help="Stop after this many seconds (default: Ctrl-C).")] = None,
    twin: Annotated[
        bool, typer.Option("--twin", help="Stream the MuJoCo + fe twin's F/T and electrodes (else constants).")
    ] = False,
    quick: Quick = False,
    sensors: Sensors = None,
    seed: Seed = 0,
    mesh_mm: MeshMm = None,
    sensor: Annotated[
        int | None, typer.Option(help="Twin: the mounted sensor (default: the first of --sensors).")
    ] = None,
    indenter: Annotated[str | None, typer.Option(help="Twin: the indenter on both flanges (required).")] = None,
) -> None:
    """Run simulated devices; print the hardware config (TOML) that points a HardwareBackend at them.

    With --twin the arms start at home and the sensors stream the twin of the plant sensor that
    `twin campaign run` with the same --quick/--sensors/--seed/--mesh-mm simulates; the config has
    0.5 s watchdogs (the twin's solves can hold up the streams for a few hundred ms).
    """
    from hardware.config import config_to_toml
    from hardware.testbed import SimulatedTestbed, driven_testbed

    left, right = _ports(egm_ports)
    options = {
        "host": host,
        "rws_port": rws_port,
        "kms40_port": kms40_port,
        "egm_ports": (left, right),
        "biotac_port": biotac_port,
        "egm_loss": egm_loss,
        "egm_delay_s": egm_delay_ms * 1e-3,
    }
    if not twin and (indenter is not None or sensor is not None):
        raise typer.BadParameter("--sensor and --indenter configure the twin; add --twin")
    twin_sources = guarded(lambda: _twin(quick, sensors, seed, mesh_mm, sensor, indenter)) if twin else None

    def start() -> SimulatedTestbed:
        try:
            if twin_sources is not None:
                return driven_testbed(twin_sources, **options)
            return SimulatedTestbed(**options)
        except PermissionError as exc:
            raise ValueError(
                f"{exc}: ports below 1024 need root; pass unprivileged ones, e.g. --rws-port 8080"
            ) from exc
        except OSError as exc:
            raise ValueError(f"cannot open a device port: {exc}") from exc

    testbed = guarded(start)
    try:
        if twin_sources is not None:
            from twin.loopback_rig import TWIN_WATCHDOG_S

            text = config_to_toml(testbed.hardware_config(watchdog_s=TWIN_WATCHDOG_S))
        else:
            text = config_to_toml(testbed.hardware_config())
        if config_out is not None:
            config_out.write_text(text)
        print(text, flush=True)
        ports = testbed.egm_ports
        if warning := exposure_warning(host):
            err_console.print(f"[bold red]{escape(warning)}[/bold red]")
        err_console.print(
            f"serving on {host}: RWS :{testbed.rws.port}, KMS40 :{testbed.kms40.port}, BioTac SPI bridge "
            f":{testbed.biotac_bridge.port}, EGM to :{ports['left']} (left) :{ports['right']} (right); Ctrl-C stops"
        )
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.1 if deadline is None else max(0.0, min(0.1, deadline - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        testbed.close()
    if twin_sources is not None:
        took = [solve.end - solve.start for solve in twin_sources.solves if solve.contact]
        err_console.print(
            f"twin: {len(took)} contact solves (slowest {max(took, default=0.0):.2f} s), "
            f"{len(twin_sources.failures)} failed"
        )
        for failure in twin_sources.failures:
            err_console.print(f"[red]twin solve failed:[/red] {escape(failure)}")


def _twin(
    quick: bool, sensors: str | None, seed: int, mesh_mm: float | None, sensor: int | None, indenter: str | None
) -> TwinSources:
    """The twin of the `twin campaign run` plant sensor (`--quick/--sensors/--seed/--mesh-mm`) `sensor`."""
    from twin.loopback_rig import TwinSources

    if indenter is None:
        raise ValueError("--twin needs --indenter NAME: the indenter mounted on the arms")
    config = campaign_config(quick, sensors, None, seed, mesh_mm)
    sensor_id = config.sensors[0] if sensor is None else sensor
    if sensor_id not in config.sensors:
        raise ValueError(f"--sensor {sensor_id} is not among the campaign's sensors {config.sensors}")
    err_console.print(f"inflating the skin of sensor {sensor_id}'s twin ...")
    return TwinSources.for_campaign(config, sensor_id, indenter)


@devices_app.command("check")
def check(
    config: Annotated[Path, typer.Argument(help="Hardware config file (.toml or .json).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Preflight: open every device of CONFIG, read one sample, report, and release them again."""
    import numpy as np

    from hardware.backend import HardwareBackend
    from hardware.config import load_config
    from twin.backend import BackendError

    cfg = guarded(lambda: load_config(config))
    try:
        backend = HardwareBackend(cfg)
    except BackendError as exc:
        err_console.print(f"[red]error:[/red] {escape(str(exc))}")
        raise typer.Exit(code=1) from exc
    try:
        sample = backend.read()
        report = {
            "joints_deg": {arm: np.degrees(q).round(3).tolist() for arm, q in sample.joints.items()},
            "wrench": sample.wrench.round(4).tolist(),
            "electrodes": sample.electrodes.astype(int).tolist(),
            "pdc": sample.pdc,
            **backend.status(),
        }
    except BackendError as exc:
        err_console.print(f"[red]error:[/red] {escape(str(exc))}")
        raise typer.Exit(code=1) from exc
    finally:
        backend.close()
    if as_json:
        print(json.dumps(report, default=str))
        return
    for key, value in report.items():
        err_console.print(f"[bold]{key}[/bold]: {value}")


@devices_app.command("config")
def config_template() -> None:
    """Print the default hardware config (the real testbed's factory addresses) as TOML to edit."""
    from hardware.config import HardwareConfig, config_to_toml

    print(config_to_toml(HardwareConfig()))
