"""Rerun views of the twin: skin, indenter, force, electrodes and series; datasets, reports, live campaigns.

`twin view` (twin/cli/view.py) logs datasets and reports; `CampaignViewer` logs a running campaign's
trajectories; the gymnasium environments log every step with `render_mode="rerun"`. docs/view.md.
"""

from twin.view.layout import default_blueprint
from twin.view.scene import SkinScene, open_recording
from twin.view.sources import CampaignViewer, log_dataset, log_path, log_report

__all__ = [
    "CampaignViewer",
    "SkinScene",
    "default_blueprint",
    "log_dataset",
    "log_path",
    "log_report",
    "open_recording",
]
