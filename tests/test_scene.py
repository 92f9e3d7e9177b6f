"""The MuJoCo testbed: FK agreement, frames of the mount, collision checks, tools, the left/right rule."""

import gzip
from pathlib import Path

import mujoco
import numpy as np
import pytest

from assets.biotac import make_biotac, outer_surface
from assets.tools import TOOLS
from twin.kinematics import forward, inverse, inverse_axis, joint_limits
from twin.scene import BIOTAC_SKIN, SceneParameters, TestbedScene, build_spec

XML_BEFORE_SPEC = Path(__file__).parent / "data" / "testbed_scene_mjcf.xml.gz"
"""The default scene's MJCF as the ElementTree builder wrote it (twin/scene.py of d735c53), before the
scene was built as an MjSpec; generated from that commit's tree, never from the code under test (session 15:
regenerated there with the texture's new fillet and jitter of assets/indenters.py, its only change; the tree
unchanged reproduces the former file byte for byte)."""
ELEMENTS = {
    "body": ("parentid", "pos", "quat", "mass", "inertia", "ipos", "iquat", "jntnum", "geomnum"),
    "jnt": ("type", "bodyid", "pos", "axis", "range", "limited", "qposadr"),
    "geom": ("type", "bodyid", "size", "pos", "quat", "rgba", "contype", "conaffinity", "group", "dataid", "rbound"),
    "site": ("bodyid", "size", "pos", "quat", "rgba"),
    "mesh": ("vertnum", "facenum", "pos", "quat"),
}
"""Per-element arrays of the compiled model compared between the two builds (MjModel `<prefix>_<name>`)."""


@pytest.fixture(scope="module")
def scene() -> TestbedScene:
    return TestbedScene()


def _site_pose(scene: TestbedScene, name: str) -> np.ndarray:
    site = scene.model.site(name).id
    pose = np.eye(4)
    pose[:3, :3] = scene.data.site_xmat[site].reshape(3, 3)
    pose[:3, 3] = scene.data.site_xpos[site]
    return pose


@pytest.mark.parametrize("arm", ["left", "right"])
def test_mujoco_tool_pose_matches_forward(scene, arm):
    rng = np.random.default_rng(0)
    lim = joint_limits(arm)
    try:
        for tool in (None, *TOOLS):
            scene.attach_tool(arm, tool)
            q = rng.uniform(lim[:, 0], lim[:, 1])
            scene.set_joints(arm, q)
            assert np.allclose(scene.tool_pose(arm), forward(arm, q, scene.tool_tip(arm)), atol=1e-10)
            assert np.allclose(scene.flange_pose(arm), forward(arm, q), atol=1e-10)
    finally:
        scene.attach_tool(arm, None)
        scene.set_joints(arm, scene.home_joints(arm))


def test_frames_of_the_mount(scene):
    assert np.allclose(_site_pose(scene, "biotac"), scene.biotac_pose, atol=1e-12)
    assert np.allclose(_site_pose(scene, "ft_sensor"), scene.ft_sensor_pose, atol=1e-12)
    holes = np.array([_site_pose(scene, f"hole_{k}")[:3, 3] for k in range(4)])
    assert np.allclose(holes, scene.hole_positions_robot, atol=1e-12)
    pose = scene.biotac_pose
    assert np.allclose(scene.hole_positions_biotac @ pose[:3, :3].T + pose[:3, 3], holes)
    assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(pose[:3, :3]), 1.0)
    # the ventral pad (biotac -z) faces up, the tip (biotac +x) points at the robot, the F/T sensor is below
    assert pose[:3, :3] @ np.array([0, 0, -1.0]) @ [0, 0, 1] > 0.99
    assert pose[:3, :3] @ np.array([1.0, 0, 0]) @ [-1, 0, 0] > 0.99
    assert scene.ft_sensor_pose[2, 3] < pose[2, 3]
    assert 0.2 < pose[0, 3] < 0.5 and abs(pose[1, 3]) < 1e-9


def test_skin_mesh_sits_at_the_biotac_pose(scene):
    geometry = make_biotac(scene.params.biotac_max_edge)
    outer = outer_surface(geometry.skin, 2 * geometry.core_gap)
    expected = outer @ scene.biotac_pose[:3, :3].T + scene.biotac_pose[:3, 3]
    geom = scene.model.geom(BIOTAC_SKIN)
    mesh = scene.model.mesh(BIOTAC_SKIN)
    local = scene.model.mesh_vert[mesh.vertadr[0] : mesh.vertadr[0] + mesh.vertnum[0]]
    world = local @ scene.data.geom_xmat[geom.id].reshape(3, 3).T + scene.data.geom_xpos[geom.id]
    assert np.allclose(np.sort(world, axis=0), np.sort(expected, axis=0), atol=1e-7)


def test_home_pose_is_collision_free(scene):
    for tool in (None, "texture", "pin"):
        for arm in ("left", "right"):
            scene.attach_tool(arm, tool)
        assert scene.collisions(allow_tool_biotac=False) == []
    for arm in ("left", "right"):
        scene.attach_tool(arm, None)


def test_arm_driven_into_the_mount_collides(scene):
    fixture = scene.model.geom("mount_fixture").id
    target = np.eye(4)
    target[:3, :3] = np.diag([1.0, -1.0, -1.0])  # flange pointing down
    target[:3, 3] = scene.data.geom_xpos[fixture]
    result = inverse("right", target, scene.home_joints("right"))
    assert result.success
    try:
        scene.set_joints("right", result.q)
        names = {name for pair in scene.collisions() for name in pair}
        assert "mount_fixture" in names
    finally:
        scene.set_joints("right", scene.home_joints("right"))


def test_indenting_the_skin_is_allowed_but_reported_on_request(scene):
    arm, tool = "right", "sphere_medium"
    pose = scene.biotac_pose
    point = np.array([-5e-3, -2e-3, -8.0e-3])  # on the ventral pad, right of the long axis
    assert scene.arm_for_point(point) == arm
    down = pose[:3, :3] @ np.array([0.0, 0.0, 1.0])  # press into the pad
    scene.attach_tool(arm, tool)
    try:
        for depth, touching in ((-3e-3, False), (1e-3, True)):
            target = pose[:3, :3] @ point + pose[:3, 3] + depth * down
            result = inverse_axis(arm, target, down, scene.home_joints(arm), scene.tool_tip(arm))
            assert result.success
            scene.set_joints(arm, result.q)
            assert scene.collisions(allow_tool_biotac=True) == []
            assert (("biotac_skin", f"{arm}_tool_{tool}") in scene.collisions(allow_tool_biotac=False)) == touching
    finally:
        scene.attach_tool(arm, None)
        scene.set_joints(arm, scene.home_joints(arm))


def test_arm_for_point_follows_the_robot_side(scene):
    assert scene.arm_for_point(np.array([-5e-3, -4e-3, -7e-3])) == "right"
    assert scene.arm_for_point(np.array([-5e-3, 4e-3, -7e-3])) == "left"
    # a point on the robot's right side (robot y < 0) belongs to the right arm
    for y in (-4e-3, 4e-3):
        p = np.array([-5e-3, y, -7e-3])
        robot = scene.biotac_pose[:3, :3] @ p + scene.biotac_pose[:3, 3]
        assert scene.arm_for_point(p) == ("right" if robot[1] < 0 else "left")


def test_set_joints_rejects_limits_and_tools_are_validated(scene):
    q = scene.home_joints("left")
    q[1] = 1.0  # joint 2 above its 0.759 rad limit
    with pytest.raises(ValueError):
        scene.set_joints("left", q)
    with pytest.raises(ValueError):
        scene.attach_tool("left", "hammer")


def test_mjcf_is_generated_and_recompiles(scene):
    xml = scene.mjcf()
    model = mujoco.MjModel.from_xml_string(xml)
    assert model.njnt == 14 and model.ngeom == scene.model.ngeom
    assert "joint_7_r" in xml and "biotac_skin" in xml


def test_spec_compiles_to_the_model_the_xml_builder_made():
    """Same names in the same order and every body/joint/geom/site/mesh array within 1e-12 (the old XML
    rounded numbers to 12 significant digits), mesh vertices and faces and contact exclusions exactly."""
    before = mujoco.MjModel.from_xml_string(gzip.decompress(XML_BEFORE_SPEC.read_bytes()).decode())
    after = build_spec(SceneParameters()).compile()
    kinds = {"body": mujoco.mjtObj.mjOBJ_BODY, "jnt": mujoco.mjtObj.mjOBJ_JOINT, "geom": mujoco.mjtObj.mjOBJ_GEOM}
    kinds |= {"site": mujoco.mjtObj.mjOBJ_SITE, "mesh": mujoco.mjtObj.mjOBJ_MESH}
    for prefix, fields in ELEMENTS.items():
        count = getattr(before, f"n{prefix}")
        assert count == getattr(after, f"n{prefix}") > 0, prefix
        names = [[mujoco.mj_id2name(m, kinds[prefix], i) for i in range(count)] for m in (before, after)]
        assert names[0] == names[1], prefix
        for name in fields:
            old, new = getattr(before, f"{prefix}_{name}"), getattr(after, f"{prefix}_{name}")
            assert old.shape == new.shape and np.allclose(old, new, rtol=0.0, atol=1e-12), f"{prefix}_{name}"
    for name in ("mesh_vert", "mesh_face", "exclude_signature"):
        assert np.array_equal(getattr(before, name), getattr(after, name)), name
    assert before.nexclude == after.nexclude == 26
