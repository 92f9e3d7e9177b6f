"""The public mesh names (NVlabs/biotac_sim ``meshes/indenters``) name our indenters everywhere a name is taken.

Independent expectations: what a public name says about its indenter (docs/indenters.md, measured on the
public meshes): the mm number is a diameter for spheres and cylinders, the full side of the cube's face,
the inner diameter of the ring; short cylinders are 7 mm long, the long one 28 mm.
"""

import re
from pathlib import Path

import pytest

from assets.indenters import (
    KIND_BOX,
    KIND_CYLINDER_SIDE,
    KIND_SPHERE,
    KIND_TORUS,
    PUBLIC_NAMES,
    get_indenter,
    indenter_name,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "indenters.md"
PUBLIC_MESHES = (
    "sphere_3-5mm",
    "sphere_7mm",
    "sphere_14mm",
    "cylinder_short_3-5mm",
    "cylinder_short_7mm",
    "cylinder_long_7mm",
    "cube_14mm",
    "ring_7mm",
)


def _size_mm(public: str) -> float:
    """The mm number of a public mesh name ("3-5mm" is 3.5 mm)."""
    return float(re.search(r"_(\d+(?:-\d+)?)mm$", public).group(1).replace("-", "."))


@pytest.mark.parametrize("public", PUBLIC_MESHES)
def test_public_name_is_the_indenter_it_names(public: str) -> None:
    ind = get_indenter(public)
    size = _size_mm(public) * 1e-3
    a, b, _, _ = ind.dims
    if public.startswith("sphere"):
        assert ind.kind == KIND_SPHERE and 2.0 * a == pytest.approx(size)
    elif public.startswith("cylinder"):
        length = 28e-3 if public.startswith("cylinder_long") else 7e-3
        assert ind.kind == KIND_CYLINDER_SIDE and 2.0 * a == pytest.approx(size) and b == pytest.approx(length)
    elif public.startswith("cube"):
        assert ind.kind == KIND_BOX and 2.0 * a == pytest.approx(size) and 2.0 * b == pytest.approx(size)
    else:
        assert ind.kind == KIND_TORUS and 2.0 * a == pytest.approx(size)


def test_alias_and_our_name_give_the_same_indenter() -> None:
    assert set(PUBLIC_NAMES) == set(PUBLIC_MESHES)
    for public in PUBLIC_MESHES:
        ours = indenter_name(public)
        assert indenter_name(ours) == ours
        assert get_indenter(public) is get_indenter(ours)
        assert get_indenter(public).name == ours


def test_docs_table_names_the_same_public_meshes() -> None:
    rows = re.findall(r"^\| (\w+) \| `([\w-]+)` \|", DOC.read_text(), flags=re.MULTILINE)
    assert len(rows) == len(PUBLIC_MESHES)
    for ours, public in rows:
        assert indenter_name(public) == ours


def test_unknown_name_lists_both_spellings() -> None:
    with pytest.raises(ValueError, match=r"unknown indenter 'sphere_99mm'.*sphere_large.*sphere_14mm"):
        get_indenter("sphere_99mm")


def test_campaign_config_takes_public_names_and_refuses_unknown_ones() -> None:
    """A campaign asked for public mesh names runs our indenters (the names the files and the plan use)."""
    from twin.campaign import CampaignConfig

    config = CampaignConfig(indenters=("sphere_14mm", "sphere_medium"))
    assert config.indenters == (indenter_name("sphere_14mm"), "sphere_medium")
    assert config.indenters[0] != "sphere_14mm"
    with pytest.raises(ValueError, match="unknown indenter"):
        CampaignConfig(indenters=("sphere_99mm",))
