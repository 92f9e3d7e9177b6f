"""The default rerun layout (blueprint) sent with every recording of the twin: skin, forces, electrodes
and residuals side by side.

Columns, left to right: the 3D skin scene of each BioTac root (`/{root}`; tabs when several); force (N),
fluid pressure (Pa) and PDC (counts) series; the 19 electrode series (tared counts); the report's
residual field on the skin (`/report`, N) above its error table. Views of entities a recording lacks stay
empty. Entity paths: docs/view.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb


def _series(roots: Sequence[str], name: str, title: str) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(name=title, origin="/series", contents=[f"/series/{root}/{name}" for root in roots])


def default_blueprint(roots: Sequence[str] = ("biotac",)) -> rrb.Blueprint:
    """The layout for the BioTac scenes under `roots` (entity roots, e.g. "biotac", "biotac2")."""
    if not roots:
        raise ValueError("the layout needs at least one BioTac root")
    skins = [rrb.Spatial3DView(name=f"{root} skin", origin=f"/{root}") for root in roots]
    return rrb.Blueprint(
        rrb.Horizontal(
            skins[0] if len(skins) == 1 else rrb.Tabs(*skins),
            rrb.Vertical(
                _series(roots, "force", "force (N)"),
                _series(roots, "pressure", "fluid pressure (Pa)"),
                _series(roots, "pdc", "PDC (counts)"),
            ),
            _series(roots, "electrodes", "electrodes (tared counts)"),
            rrb.Vertical(
                rrb.Spatial3DView(name="residual field (N)", origin="/report"),
                rrb.TextDocumentView(name="report errors", origin="/report/summary"),
                row_shares=[3, 1],
            ),
            column_shares=[3, 2, 2, 3],
        ),
    )
