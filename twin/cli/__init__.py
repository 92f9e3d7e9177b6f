"""The `twin` command line: one root app; each command group lives in its own module of this package.

A module's `typer.Typer` is added by `add_typer`: with a name it is a group (`twin fe ...`), without one its
commands sit at the top level (`twin compare`). `twin --help` lists them in the order added here: the skin
model, campaigns and their data, the model-vs-measurement analysis and loop, views and export, learned
models, devices.
"""

import typer

from twin.cli.analysis import analysis_app
from twin.cli.calibrate import calibrate_app
from twin.cli.campaign import campaign_app
from twin.cli.dataset import dataset_app
from twin.cli.devices import devices_app
from twin.cli.export import export_app
from twin.cli.fe import fe_app
from twin.cli.learn import learn_app
from twin.cli.loop import loop_app
from twin.cli.view import view_app

app = typer.Typer(help="biotac-twin: digital twin of the robotic BioTac indentation testbed.", no_args_is_help=True)
app.add_typer(fe_app, name="fe")
app.add_typer(campaign_app, name="campaign")
app.add_typer(dataset_app, name="dataset")
app.add_typer(analysis_app)
app.add_typer(calibrate_app)
app.add_typer(loop_app)
app.add_typer(view_app)
app.add_typer(export_app)
app.add_typer(learn_app, name="learn")
app.add_typer(devices_app, name="devices")
