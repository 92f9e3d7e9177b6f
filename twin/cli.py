"""The `twin` command line: one entry point; each capability's subcommands live in their own module."""

import typer

from twin.cli_analysis import analysis_app
from twin.cli_calibrate import calibrate_app
from twin.cli_campaign import campaign_app, dataset_app
from twin.cli_devices import devices_app
from twin.cli_export import export_app
from twin.cli_fe import fe_app
from twin.cli_learn import learn_app
from twin.cli_loop import loop_app
from twin.cli_view import view_app

app = typer.Typer(help="biotac-twin: digital twin of the robotic BioTac indentation testbed.", no_args_is_help=True)
app.add_typer(fe_app, name="fe")
app.add_typer(learn_app, name="learn")
app.add_typer(devices_app, name="devices")
app.add_typer(campaign_app, name="campaign")
app.add_typer(dataset_app, name="dataset")
app.registered_commands += analysis_app.registered_commands
app.registered_commands += loop_app.registered_commands
app.registered_commands += calibrate_app.registered_commands
app.registered_commands += view_app.registered_commands
app.registered_commands += export_app.registered_commands
