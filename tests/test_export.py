"""`twin export`: the BioTac (and the testbed) as MJCF that MuJoCo loads and URDF that a URDF reader walks.

Expectations from outside the exporter: the product manual's electrode table (positions, outward normals,
biotac frame), the skin's outer surface and the core from ``assets.biotac``, the mount placement from
``twin.scene``/``assets.mount``, the YuMi joint limits from ``assets.yumi``; and MuJoCo's own forward
kinematics for the URDF frames (the two formats must agree on every frame).
"""

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from assets.biotac import DEFAULT_DIMENSIONS, electrode_table, make_core, make_skin, outer_surface
from assets.yumi import ARM_CHAINS
from twin.cli import app
from twin.scene import SceneParameters, mount_pose

PARAMS = SceneParameters()


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[str, Path]:
    """The four exports, each through the CLI."""
    folder = tmp_path_factory.mktemp("export")
    paths = {}
    for fmt, suffix in (("mjcf", "xml"), ("urdf", "urdf")):
        for testbed in (False, True):
            out = folder / f"{'testbed' if testbed else 'biotac'}.{suffix}"
            args = ["export", "--format", fmt, "--out", str(out)] + (["--testbed"] if testbed else [])
            result = CliRunner().invoke(app, args)
            assert result.exit_code == 0, result.output
            paths[fmt, testbed] = out
    return paths


def _loaded(path: Path) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def _pose(pos: np.ndarray, mat: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = np.reshape(mat, (3, 3)), pos
    return t


def _biotac_from_world(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    b = model.body("biotac").id
    return np.linalg.inv(_pose(data.xpos[b], data.xmat[b]))


def _apply(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ t[:3, :3].T + t[:3, 3]


def _electrode_frames(model: mujoco.MjModel, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
    """Electrode site positions (19, 3) and z axes (19, 3) in the biotac frame."""
    to_biotac = _biotac_from_world(model, data)
    ids = [model.site(f"electrode_{k}").id for k in range(1, 20)]
    pos = _apply(to_biotac, data.site_xpos[ids])
    z_axes = data.site_xmat[ids].reshape(-1, 3, 3)[:, :, 2] @ to_biotac[:3, :3].T
    return pos, z_axes


@pytest.mark.parametrize("testbed", [False, True])
def test_mjcf_loads_with_the_19_electrodes_of_the_manual(exported, testbed: bool) -> None:
    model, data = _loaded(exported["mjcf", testbed])
    names = [model.site(s).name for s in range(model.nsite)]
    assert sum(n.startswith("electrode_") for n in names) == 19
    pos, z_axes = _electrode_frames(model, data)
    table = electrode_table()
    np.testing.assert_allclose(pos, table.positions, atol=1e-8)  # MJCF numbers carry 6 significant digits
    np.testing.assert_allclose(z_axes, table.normals, atol=2e-6)


def test_mjcf_skin_and_core_are_the_assets_meshes(exported) -> None:
    model, data = _loaded(exported["mjcf", False])
    to_biotac = _biotac_from_world(model, data)
    d = DEFAULT_DIMENSIONS
    skin = make_skin(PARAMS.biotac_max_edge, d)
    core = make_core(PARAMS.biotac_max_edge, d)
    expected = {"biotac_skin": outer_surface(skin, d.skin_thickness), "biotac_core": core.vertices}
    for name, want in expected.items():
        g = model.geom(name).id
        m = int(model.geom_dataid[g])
        local = model.mesh_vert[model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        got = _apply(to_biotac @ _pose(data.geom_xpos[g], data.geom_xmat[g]), local.astype(float))
        assert got.shape == want.shape
        np.testing.assert_allclose(np.sort(got, axis=0), np.sort(want, axis=0), atol=2e-7)
    assert model.nmesh == 2  # no indenter meshes on the BioTac alone


def test_mjcf_testbed_places_the_biotac_on_the_mount_with_no_tool(exported) -> None:
    model, data = _loaded(exported["mjcf", True])
    b = model.body("biotac").id
    np.testing.assert_allclose(
        _pose(data.xpos[b], data.xmat[b]), mount_pose(PARAMS) @ PARAMS.mount.biotac_in_mount(), atol=1e-9
    )
    assert model.njnt == 14
    assert not any("_tool_" in model.geom(g).name for g in range(model.ngeom))


def _rpy_matrix(rpy: list[float]) -> np.ndarray:
    r, p, y = rpy
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _origin(element: ET.Element) -> np.ndarray:
    origin = element.find("origin")
    t = np.eye(4)
    if origin is not None:
        t[:3, :3] = _rpy_matrix([float(v) for v in origin.get("rpy", "0 0 0").split()])
        t[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    return t


def _link_poses(root: ET.Element) -> dict[str, np.ndarray]:
    """World pose of every link at zero joint angles, walking the tree from its one root."""
    links = {link.get("name") for link in root.findall("link")}
    joints = root.findall("joint")
    children = [j.find("child").get("link") for j in joints]
    assert len(children) == len(set(children)), "a link with two parents"
    assert {j.find("parent").get("link") for j in joints} | set(children) <= links
    (base,) = links - set(children)
    poses = {base: np.eye(4)}
    pending = list(joints)
    while pending:
        ready = [j for j in pending if j.find("parent").get("link") in poses]
        assert ready, "joints not connected to the root"
        for j in ready:
            poses[j.find("child").get("link")] = poses[j.find("parent").get("link")] @ _origin(j)
            pending.remove(j)
    assert set(poses) == links
    return poses


@pytest.mark.parametrize("testbed", [False, True])
def test_urdf_frames_agree_with_mujoco(exported, testbed: bool) -> None:
    root = ET.parse(exported["urdf", testbed]).getroot()
    poses = _link_poses(root)
    model, data = _loaded(exported["mjcf", testbed])
    tol = 2e-6  # MJCF numbers carry 6 significant digits: ~1e-6 rad down the arm chains
    for b in range(1, model.nbody):
        np.testing.assert_allclose(poses[model.body(b).name], _pose(data.xpos[b], data.xmat[b]), atol=tol)
    for s in range(model.nsite):
        want = _pose(data.site_xpos[s], data.site_xmat[s])
        np.testing.assert_allclose(poses[f"{model.site(s).name}_frame"], want, atol=tol)


def test_urdf_meshes_load_and_sit_in_the_biotac_frame(exported) -> None:
    path = exported["urdf", False]
    root = ET.parse(path).getroot()
    (biotac,) = [link for link in root.findall("link") if link.get("name") == "biotac"]
    files = {
        v.get("name"): v.find("geometry/mesh").get("filename")
        for v in biotac.findall("visual")
        if v.find("geometry/mesh") is not None
    }
    assert set(files) == {"biotac_skin", "biotac_core"}
    d = DEFAULT_DIMENSIONS
    skin = trimesh.load(path.parent / files["biotac_skin"])  # merges the STL corners into vertices
    core = trimesh.load(path.parent / files["biotac_core"])
    want = outer_surface(make_skin(PARAMS.biotac_max_edge, d), d.skin_thickness)
    np.testing.assert_allclose(np.sort(skin.vertices, axis=0), np.sort(want, axis=0), atol=2e-7)
    assert core.is_watertight and core.volume > 0.0


def test_urdf_testbed_has_the_yumi_joints_and_limits(exported) -> None:
    root = ET.parse(exported["urdf", True]).getroot()
    revolute = {j.get("name"): j for j in root.findall("joint") if j.get("type") == "revolute"}
    specs = [spec for chain in ARM_CHAINS.values() for spec in chain.joints]
    assert set(revolute) == {spec.name for spec in specs}
    for spec in specs:
        limit = revolute[spec.name].find("limit")
        assert float(limit.get("lower")) == pytest.approx(spec.lower)
        assert float(limit.get("upper")) == pytest.approx(spec.upper)


@pytest.mark.parametrize(
    "args",
    [
        ["--format", "stl", "--out", "x.stl"],
        ["--format", "mjcf", "--out", "/no/such/folder/x.xml"],
    ],
)
def test_bad_export_arguments_are_one_line_errors(args: list[str]) -> None:
    result = CliRunner().invoke(app, ["export", *args])
    assert result.exit_code == 2
    assert "error:" in result.output and "Traceback" not in result.output
