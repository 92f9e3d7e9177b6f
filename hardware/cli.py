"""`twin devices ...`: simulated YuMi (EGM + RWS), KMS40 and BioTac devices on loopback."""

import typer

devices_app = typer.Typer(help="Simulated devices that speak the real wire protocols.", no_args_is_help=True)
