"""`twin learn ...`: train, evaluate and apply the electrode models (torch is imported lazily)."""

import typer

learn_app = typer.Typer(help="Learned electrode models: train, eval, predict.", no_args_is_help=True)
