"""The testbed in MuJoCo: both YuMi arms, the mount with its F/T sensor, the BioTac and the flange tools.

The model is built as a ``mujoco.MjSpec`` (``build_spec``) from parameters (``SceneParameters``): arm
chains from ``assets.yumi``, mount from ``assets.mount``, skin and core meshes from ``assets.biotac``,
indenter meshes from ``assets.indenters``, tool placement from ``assets.tools``. No XML is written to
build it; ``TestbedScene.mjcf()`` and ``twin export`` write the spec's MJCF.

Frames: MuJoCo's world frame *is* the robot frame (``twin.kinematics``): the YuMi body sits at the
origin, the bench top is z = 0. The mount stands on the bench in front of the robot; the BioTac lies
horizontally on it, pad up, tip pointing at the robot (see ``assets.mount`` and docs/testbed.md).

MuJoCo is used kinematically only: joint positions are set, never simulated. Collision checks are
MuJoCo's narrow phase on the primitives and on convex hulls of the meshes (so the ring and the texture
indenter collide as their hulls). Every tool is compiled onto both flanges once and switched on or off
by its collision bits, so attaching a tool is cheap and the model never needs rebuilding.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from assets.biotac import make_biotac, make_core, outer_surface
from assets.indenters import INDENTERS, get_indenter
from assets.mount import MountGeometry
from assets.tools import DEFAULT_PIN, PIN, TOOLS, PinGeometry, tool_tip_transform
from assets.yumi import ARM_CHAINS, HOME_JOINTS, NEIGHBOUR_EXCLUDE, TORSO_SHAPES, Shape, link_shapes
from twin.backend import ARMS, N_JOINTS, check_arm
from twin.kinematics import origin_transform, within_limits

BIOTAC_SKIN = "biotac_skin"
"""Geom name of the BioTac's outer skin (collides as the convex hull of the unpressurised outer surface)."""


@dataclass(frozen=True)
class SceneParameters:
    """Everything the scene is made from (SI units).

    mount_position: (3,) m, the mount frame's origin (base plate underside centre) in the robot frame;
    mount_yaw: rad about the robot z axis (0: mount x points away from the robot). biotac_max_edge and
    tool_max_edge: mesh resolution (m) of the BioTac skin/core and of the indenter meshes.
    adapter_length: spacer (m) between flange and indenter (``assets.tools``).
    """

    mount: MountGeometry = field(default_factory=MountGeometry)
    mount_position: tuple[float, float, float] = (0.38, 0.0, 0.0)
    mount_yaw: float = 0.0
    biotac_max_edge: float = 2e-3
    tool_max_edge: float = 2e-3
    pin: PinGeometry = DEFAULT_PIN
    adapter_length: float = 0.0


def mount_pose(params: SceneParameters) -> np.ndarray:
    """(4, 4) robot <- mount transform of `params`."""
    return origin_transform(params.mount_position, (0.0, 0.0, params.mount_yaw))


def arm_for_point(point_biotac: np.ndarray, biotac_pose: np.ndarray) -> str:
    """Which arm indents a point (3,) given in the biotac frame (m): the paper's left/right rule.

    Seen from the robot, a point right of the BioTac's long axis (the biotac x axis through the origin)
    goes to the right arm, a point left of it to the left arm: the point's offset from the axis,
    mapped to the robot frame by `biotac_pose` (robot <- biotac), is tested against the robot's right
    direction (-y). A point exactly on the axis goes left. With the default mount (biotac y = robot y)
    this is "right" exactly when the point's biotac y < 0.
    """
    rot = np.asarray(biotac_pose, dtype=float)[:3, :3]
    axis = rot[:, 0]
    v = rot @ np.asarray(point_biotac, dtype=float)
    lateral = v - (v @ axis) * axis
    return "right" if -lateral[1] > 0.0 else "left"


GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
}
"""MuJoCo geom type of each ``assets.yumi.Shape`` kind."""

Placed = mujoco.MjsBody | mujoco.MjsGeom | mujoco.MjsSite


def _place(element: Placed, transform: np.ndarray) -> None:
    """Set pos (m) and quat (w, x, y, z) of a spec element from a (4, 4) parent <- element transform."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(transform[:3, :3], dtype=float).ravel())
    element.pos, element.quat = transform[:3, 3], quat


def _site(body: mujoco.MjsBody, name: str, radius: float, transform: np.ndarray | None = None) -> mujoco.MjsSite:
    """A sphere site of `radius` (m) on `body`, placed by `transform` (4, 4) body <- site (origin if None)."""
    site = body.add_site(name=name)
    site.size[0] = radius  # the other two sizes keep MuJoCo's defaults (unused by a sphere)
    if transform is not None:
        _place(site, transform)
    return site


def _shape_geom(body: mujoco.MjsBody, shape: Shape, rgba: tuple[float, ...], prefix: str = "") -> mujoco.MjsGeom:
    """Add the geom of `shape` (assets.yumi.Shape, body frame) to `body`: visual ones in group 1 without
    collision bits, colliding ones in group 3."""
    geom = body.add_geom(name=prefix + shape.name, type=GEOM_TYPES[shape.kind], rgba=rgba)
    if shape.kind == "box":
        geom.size, geom.pos = shape.size, shape.a
    else:
        geom.size[0] = shape.size[0]
        geom.fromto = (*shape.a, *shape.b)
    geom.group = 3 if shape.collide else 1
    if not shape.collide:
        geom.contype = geom.conaffinity = 0
    return geom


def _mesh_asset(spec: mujoco.MjSpec, name: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A mesh asset `name` of vertices (V, 3) m and triangles (T, 3)."""
    spec.add_mesh(name=name, uservert=np.ravel(vertices).tolist(), userface=np.ravel(faces).astype(int).tolist())


def _tool_geoms(link7: mujoco.MjsBody, arm: str, params: SceneParameters, flange: np.ndarray) -> None:
    """Every tool on `arm`'s flange. They compile as colliding (so MuJoCo builds their convex hulls);
    ``TestbedScene`` switches them off (collision bits 0, transparent) until attached."""
    colour = (0.8, 0.6, 0.2, 1.0)
    for tool in TOOLS:
        tip = flange @ tool_tip_transform(tool, params.adapter_length, params.pin)
        if tool == PIN:
            pin, cylinder = params.pin, mujoco.mjtGeom.mjGEOM_CYLINDER
            shaft_size = [pin.shaft_radius, 0.5 * (pin.shaft_length - 5e-4), 0.0]
            shaft = link7.add_geom(name=f"{arm}_tool_pin_shaft", type=cylinder, size=shaft_size, rgba=colour)
            _place(shaft, tip @ origin_transform((0, 0, 0.5 * (pin.shaft_length + 5e-4)), (0, 0, 0)))
            nose_size = [pin.nose_radius, 0.5 * pin.nose_length, 0.0]
            nose = link7.add_geom(name=f"{arm}_tool_pin_nose", type=cylinder, size=nose_size, rgba=colour)
            _place(nose, tip @ origin_transform((0, 0, -0.5 * pin.nose_length), (0, 0, 0)))
            geoms = (shaft, nose)
        else:
            geom = link7.add_geom(
                name=f"{arm}_tool_{tool}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"tool_{tool}", rgba=colour
            )
            _place(geom, tip)
            geoms = (geom,)
        for geom in geoms:
            geom.group = 1


def _arm_bodies(parent: mujoco.MjsBody, arm: str, params: SceneParameters) -> None:
    """`arm`'s chain of links (one hinge each, about the link's z axis, with its limits in rad), its flange
    and tool-tip sites, and every tool, below `parent`."""
    chain = ARM_CHAINS[arm]
    body = parent
    for i, (joint, shapes) in enumerate(zip(chain.joints, link_shapes(arm), strict=True)):
        body = body.add_body(name=f"{arm}_link_{i + 1}")
        _place(body, origin_transform(joint.xyz, joint.rpy))
        body.add_joint(name=joint.name, axis=[0.0, 0.0, 1.0], range=[joint.lower, joint.upper])
        for shape in shapes:
            _shape_geom(body, shape, (0.85, 0.85, 0.85, 1.0))
    flange = origin_transform(chain.flange_xyz, chain.flange_rpy)
    _site(body, f"{arm}_flange", 0.004, flange)
    _site(body, f"{arm}_tip", 0.002, flange).rgba = (1.0, 0.0, 0.0, 1.0)
    _tool_geoms(body, arm, params, flange)


def build_spec(params: SceneParameters) -> mujoco.MjSpec:
    """The MuJoCo spec of the whole testbed described by `params` (world = robot frame, m, rad)."""
    spec = mujoco.MjSpec()
    spec.modelname = "biotac_testbed"
    spec.compiler.degree = False
    spec.compiler.autolimits = True
    biotac = make_biotac(params.biotac_max_edge)
    _mesh_asset(spec, BIOTAC_SKIN, outer_surface(biotac.skin, 2.0 * biotac.core_gap), biotac.skin.triangles)
    core = make_core(params.biotac_max_edge, biotac.dims)
    _mesh_asset(spec, "biotac_core", core.vertices, core.triangles)
    for name, indenter in INDENTERS.items():
        hull = get_indenter(indenter.name).mesh(params.tool_max_edge).convex_hull
        _mesh_asset(spec, f"tool_{name}", hull.vertices, hull.faces)

    world = spec.worldbody
    world.add_geom(name="bench", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1.0, 1.0, 0.01], rgba=[0.6, 0.5, 0.4, 1.0])
    torso = world.add_body(name="yumi_body")
    for shape in TORSO_SHAPES:
        _shape_geom(torso, shape, (0.7, 0.7, 0.75, 1.0))
    for arm in ARMS:
        _arm_bodies(torso, arm, params)

    mount = world.add_body(name="mount")
    _place(mount, mount_pose(params))
    for shape in params.mount.shapes():
        _shape_geom(mount, shape, (0.3, 0.3, 0.35, 1.0), "mount_")
    _site(mount, "ft_sensor", 0.005, params.mount.ft_sensor_in_mount())
    for k, hole in enumerate(params.mount.holes_in_mount()):
        _site(mount, f"hole_{k}", 0.002).pos = hole
    body = mount.add_body(name="biotac")
    _place(body, params.mount.biotac_in_mount())
    _site(body, "biotac", 0.003)
    mesh = mujoco.mjtGeom.mjGEOM_MESH
    body.add_geom(name=BIOTAC_SKIN, type=mesh, meshname=BIOTAC_SKIN, rgba=[0.9, 0.75, 0.6, 0.8])
    core_rgba = [0.2, 0.2, 0.2, 1.0]
    body.add_geom(
        name="biotac_core", type=mesh, meshname="biotac_core", contype=0, conaffinity=0, group=1, rgba=core_rgba
    )
    _shape_geom(body, params.mount.biotac_base_shape(), (0.2, 0.2, 0.2, 1.0))

    for arm in ARMS:
        for link in (1, 2):
            spec.add_exclude(bodyname1="yumi_body", bodyname2=f"{arm}_link_{link}")
        for i in range(1, N_JOINTS + 1):
            for j in range(i + 1, min(i + NEIGHBOUR_EXCLUDE, N_JOINTS) + 1):
                spec.add_exclude(bodyname1=f"{arm}_link_{i}", bodyname2=f"{arm}_link_{j}")
    return spec


class TestbedScene:
    """The MuJoCo testbed built from `params`; holds one configuration of both arms and their tools.

    Poses are 4x4 homogeneous transforms in the robot frame (m). Joint vectors are (7,) rad, chain order.
    """

    __test__ = False  # not a pytest class

    def __init__(self, params: SceneParameters | None = None) -> None:
        self.params = params if params is not None else SceneParameters()
        self.spec = build_spec(self.params)
        self.model = self.spec.compile()
        self.data = mujoco.MjData(self.model)
        self._qpos = {
            arm: np.array([self.model.jnt_qposadr[self.model.joint(j.name).id] for j in ARM_CHAINS[arm].joints])
            for arm in ARMS
        }
        self._tip_site = {arm: self.model.site(f"{arm}_tip").id for arm in ARMS}
        self._flange_site = {arm: self.model.site(f"{arm}_flange").id for arm in ARMS}
        self._tool_geoms = {
            (arm, tool): [
                self.model.geom(name).id
                for name in (
                    (f"{arm}_tool_pin_shaft", f"{arm}_tool_pin_nose") if tool == PIN else (f"{arm}_tool_{tool}",)
                )
            ]
            for arm in ARMS
            for tool in TOOLS
        }
        self._tool_owner = {g: arm for (arm, _), ids in self._tool_geoms.items() for g in ids}
        self._skin_geom = self.model.geom(BIOTAC_SKIN).id
        self._pin_nose = {self.model.geom(f"{arm}_tool_pin_nose").id for arm in ARMS}
        self._tools: dict[str, str | None] = {arm: None for arm in ARMS}
        self._biotac_pose = mount_pose(self.params) @ self.params.mount.biotac_in_mount()
        self.reset()

    def reset(self) -> None:
        """Back to the state a new scene starts in (no tools, both arms at home): the same model and data
        values as a scene built afresh, for a fraction of the build's cost (about 1 s at the 2 mm mesh)."""
        for arm in ARMS:
            self.attach_tool(arm, None)
            self.set_joints(arm, self.home_joints(arm))

    def mjcf(self) -> str:
        """The MJCF text of this scene's spec (meshes inline)."""
        return self.spec.to_xml()

    @property
    def biotac_pose(self) -> np.ndarray:
        """(4, 4) true robot <- biotac transform H_RB of the mount (p_robot = H_RB @ p_biotac)."""
        return self._biotac_pose.copy()

    @property
    def ft_sensor_pose(self) -> np.ndarray:
        """(4, 4) robot <- F/T sensor frame (KMS40 top face centre, axes parallel to the mount's)."""
        return mount_pose(self.params) @ self.params.mount.ft_sensor_in_mount()

    @property
    def hole_positions_biotac(self) -> np.ndarray:
        """(4, 3) liner rim centres (where the pin shoulder sits) in the biotac frame, m (the "CAD" points)."""
        holes = self.params.mount.holes_in_mount()
        to_biotac = np.linalg.inv(self.params.mount.biotac_in_mount())
        return holes @ to_biotac[:3, :3].T + to_biotac[:3, 3]

    @property
    def hole_positions_robot(self) -> np.ndarray:
        """(4, 3) the same hole points in the robot frame, m (true mount pose)."""
        return self.hole_positions_biotac @ self._biotac_pose[:3, :3].T + self._biotac_pose[:3, 3]

    def arm_for_point(self, point_biotac: np.ndarray) -> str:
        """ "left" or "right": the arm that indents `point_biotac` (3,) m (see module `arm_for_point`)."""
        return arm_for_point(point_biotac, self._biotac_pose)

    def home_joints(self, arm: str) -> np.ndarray:
        """(7,) rad: `arm`'s parking configuration (ABB's synchronisation pose), clear of everything."""
        return HOME_JOINTS[check_arm(arm)].copy()

    def joints(self, arm: str) -> np.ndarray:
        """(7,) rad: `arm`'s current joint vector."""
        return self.data.qpos[self._qpos[check_arm(arm)]].copy()

    def set_joints(self, arm: str, q: np.ndarray) -> None:
        """Put `arm` at joint vector q (7,) rad; ValueError outside the joint limits."""
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,) or not within_limits(check_arm(arm), q, tol=1e-9):
            raise ValueError(f"set_joints: {arm} joint vector {q!r} has the wrong shape or violates the limits")
        self.data.qpos[self._qpos[arm]] = q
        mujoco.mj_kinematics(self.model, self.data)

    def tool(self, arm: str) -> str | None:
        """The tool now attached to `arm`'s flange (an indenter name, "pin") or None."""
        return self._tools[check_arm(arm)]

    def tool_tip(self, arm: str) -> np.ndarray:
        """(4, 4) flange -> tip transform of `arm`'s current tool (identity without a tool)."""
        tool = self._tools[check_arm(arm)]
        return np.eye(4) if tool is None else tool_tip_transform(tool, self.params.adapter_length, self.params.pin)

    def attach_tool(self, arm: str, tool: str | None) -> None:
        """Mount `tool` (an indenter name, "pin", or None) on `arm`'s flange, replacing the previous one."""
        check_arm(arm)
        if tool is not None and tool not in TOOLS:
            raise ValueError(f"unknown tool {tool!r}; valid tools: {', '.join(TOOLS)}")
        for (owner, name), ids in self._tool_geoms.items():
            if owner != arm:
                continue
            on = name == tool
            for g in ids:
                collide = on and g not in self._pin_nose  # the nose enters the liner: visual only
                self.model.geom_contype[g] = self.model.geom_conaffinity[g] = int(collide)
                self.model.geom_rgba[g, 3] = 1.0 if on else 0.0
        self._tools[arm] = tool
        flange = origin_transform(ARM_CHAINS[arm].flange_xyz, ARM_CHAINS[arm].flange_rpy)
        tip = flange @ self.tool_tip(arm)
        site = self._tip_site[arm]
        self.model.site_pos[site] = tip[:3, 3]
        mujoco.mju_mat2Quat(self.model.site_quat[site], np.ascontiguousarray(tip[:3, :3]).ravel())
        mujoco.mj_kinematics(self.model, self.data)

    def _site_pose(self, site: int) -> np.ndarray:
        pose = np.eye(4)
        pose[:3, :3] = self.data.site_xmat[site].reshape(3, 3)
        pose[:3, 3] = self.data.site_xpos[site]
        return pose

    def tool_pose(self, arm: str) -> np.ndarray:
        """(4, 4) robot-frame pose of `arm`'s tool tip (the flange without a tool), from MuJoCo."""
        return self._site_pose(self._tip_site[check_arm(arm)])

    def flange_pose(self, arm: str) -> np.ndarray:
        """(4, 4) robot-frame pose of `arm`'s flange, from MuJoCo."""
        return self._site_pose(self._flange_site[check_arm(arm)])

    def collisions(self, allow_tool_biotac: bool = True) -> list[tuple[str, str]]:
        """Sorted unique pairs of geom names in contact or penetrating in the current configuration.

        allow_tool_biotac: leave out contacts between an attached tool and the BioTac skin (indenting).
        """
        mujoco.mj_collision(self.model, self.data)
        pairs = set()
        for contact in self.data.contact[: self.data.ncon]:
            g1, g2 = int(contact.geom1), int(contact.geom2)
            if allow_tool_biotac and self._skin_geom in (g1, g2) and (g1 in self._tool_owner or g2 in self._tool_owner):
                continue
            pairs.add(tuple(sorted((self.model.geom(g1).name, self.model.geom(g2).name))))
        return sorted(pairs)
