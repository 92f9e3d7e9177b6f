"""The BioTac on its mount (optionally the whole testbed) for other simulators: MJCF and URDF.

One source: the scene's ``mujoco.MjSpec`` (``twin.scene.build_spec``), trimmed to the mount
and the BioTac (or, with the testbed, kept whole with no tool on the flanges), plus one site per electrode
(``electrode_1`` ... ``electrode_19``, z axis along the electrode's outward normal, product-manual order).
The BioTac is its skin's outer surface (unpressurised), its rigid core, its base and the mount with the
F/T sensor. MJCF is the spec's XML (meshes inline). URDF is written from the compiled model: one link per
body (revolute joints for the arm hinges, fixed joints otherwise), one fixed child link per site
(``<site>_frame``), geoms as visuals (and collisions where they collide; a capsule becomes a cylinder and two
spheres, the bench plane a 1 mm slab under z = 0), meshes as STL files in ``<name>_meshes/`` beside the
URDF. Units: metres, radians; frames as in ``twin.scene`` (world = robot frame).
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import trimesh

from assets.biotac import electrode_table
from twin.scene import SceneParameters, build_spec

FORMATS = ("mjcf", "urdf")
ELECTRODE_SITE_RADIUS = 0.5e-3
"""Radius (m) of the electrode sites (display only)."""
BENCH_SLAB = 1e-3
"""Thickness (m) of the slab that stands in for the bench plane in URDF."""


def export_spec(params: SceneParameters, testbed: bool = False) -> mujoco.MjSpec:
    """MjSpec of the BioTac on its mount at the world origin, or of the testbed (`testbed`), with electrode sites."""
    spec = build_spec(params)
    spec.modelname = "biotac_testbed" if testbed else "biotac"
    for geom in [g for g in spec.geoms if "_tool_" in g.name]:
        spec.delete(geom)
    for mesh in [m for m in spec.meshes if m.name.startswith("tool_")]:
        spec.delete(mesh)
    if not testbed:
        for exclude in list(spec.excludes):
            spec.delete(exclude)
        spec.delete(spec.body("yumi_body"))
        spec.delete(spec.geom("bench"))
        mount = spec.body("mount")
        mount.pos, mount.quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    biotac = spec.body("biotac")
    electrodes = electrode_table()
    for k, (position, normal) in enumerate(zip(electrodes.positions, electrodes.normals, strict=True)):
        quat = np.empty(4)
        mujoco.mju_quatZ2Vec(quat, np.ascontiguousarray(normal, dtype=float))
        biotac.add_site(
            name=f"electrode_{k + 1}",
            pos=position,
            quat=quat,
            size=[ELECTRODE_SITE_RADIUS, 0.0, 0.0],
            rgba=[0.1, 0.4, 0.9, 1.0],
        )
    return spec


def write_mjcf(spec: mujoco.MjSpec, out: Path) -> None:
    """Compile `spec` (so a broken model fails here) and write its MJCF to `out`."""
    spec.compile()
    out.write_text(spec.to_xml())


def _vec(values, digits: int = 9) -> str:
    return " ".join(f"{float(v) + 0.0:.{digits}g}" for v in np.ravel(values))  # + 0.0: no "-0"


def _rpy(quat: np.ndarray) -> np.ndarray:
    """URDF roll-pitch-yaw (R = Rz(y) Ry(p) Rx(r)) of a MuJoCo (w, x, y, z) quaternion."""
    r = np.empty(9)
    mujoco.mju_quat2Mat(r, np.ascontiguousarray(quat, dtype=float))
    r = r.reshape(3, 3)
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        return np.array([np.arctan2(r[2, 1], r[2, 2]), pitch, np.arctan2(r[1, 0], r[0, 0])])
    return np.array([0.0, pitch, np.arctan2(-r[0, 1], r[1, 1])])  # gimbal lock: roll folded into yaw


def _origin(parent: ET.Element, pos: np.ndarray, quat: np.ndarray) -> None:
    ET.SubElement(parent, "origin", xyz=_vec(pos), rpy=_vec(_rpy(quat)))


def _rotate(quat: np.ndarray, local: np.ndarray) -> np.ndarray:
    """R(`quat`) @ `local` for one point (3,)."""
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.ascontiguousarray(local, dtype=float), np.ascontiguousarray(quat, dtype=float))
    return out


def _geometry_parts(model: mujoco.MjModel, g: int, mesh_file: str | None) -> list[tuple[np.ndarray, ET.Element]]:
    """URDF <geometry> of geom `g`, each part with its centre in the geom frame (m): one, or three for a capsule.

    A mesh geom's file holds its vertices in the body frame already (`mesh_file`)."""
    kind, size = mujoco.mjtGeom(int(model.geom_type[g])), model.geom_size[g]
    geometry = ET.Element("geometry")
    centre = np.zeros(3)
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        ET.SubElement(geometry, "box", size=_vec(2.0 * size))
    elif kind == mujoco.mjtGeom.mjGEOM_PLANE:
        ET.SubElement(geometry, "box", size=_vec([2.0 * size[0], 2.0 * size[1], BENCH_SLAB]))
        centre = np.array([0.0, 0.0, -0.5 * BENCH_SLAB])
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        ET.SubElement(geometry, "sphere", radius=_vec(size[:1]))
    elif kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE):
        ET.SubElement(geometry, "cylinder", radius=_vec(size[:1]), length=_vec([2.0 * size[1]]))
    elif kind == mujoco.mjtGeom.mjGEOM_MESH and mesh_file is not None:
        ET.SubElement(geometry, "mesh", filename=mesh_file)
    else:
        raise ValueError(f"geom {model.geom(g).name!r}: type {kind.name} has no URDF counterpart")
    parts = [(centre, geometry)]
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        for end in (-1.0, 1.0):
            cap = ET.Element("geometry")
            ET.SubElement(cap, "sphere", radius=_vec(size[:1]))
            parts.append((np.array([0.0, 0.0, end * size[1]]), cap))
    return parts


def _mesh_file(model: mujoco.MjModel, g: int, folder: Path) -> str:
    """Write mesh geom `g` as an STL in its body's frame (m) into `folder`; its path relative to the URDF."""
    m = int(model.geom_dataid[g])
    v0, nv, f0, nf = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, np.ascontiguousarray(model.geom_quat[g], dtype=float))
    vertices = model.mesh_vert[v0 : v0 + nv].astype(float) @ rot.reshape(3, 3).T + model.geom_pos[g]
    path = folder / f"{model.geom(g).name}.stl"
    trimesh.Trimesh(vertices, model.mesh_face[f0 : f0 + nf], process=False).export(path)
    return f"{folder.name}/{path.name}"


def _link_geoms(link: ET.Element, model: mujoco.MjModel, body: int, mesh_folder: Path) -> None:
    for g in np.flatnonzero(model.geom_bodyid == body):
        name = model.geom(g).name
        if int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_MESH):
            mesh_file, pos, quat = _mesh_file(model, g, mesh_folder), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        else:
            mesh_file, pos, quat = None, model.geom_pos[g], model.geom_quat[g]
        collides = model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0
        for centre, geometry in _geometry_parts(model, g, mesh_file):
            for tag in ("visual", "collision") if collides else ("visual",):
                element = ET.SubElement(link, tag, name=name)
                _origin(element, pos + _rotate(quat, centre), quat)
                element.append(copy.deepcopy(geometry))
                if tag == "visual":
                    material = ET.SubElement(element, "material", name=f"{name}_colour")
                    ET.SubElement(material, "color", rgba=_vec(model.geom_rgba[g], digits=4))


def _joint(robot: ET.Element, name: str, kind: str, parent: str, child: str, pos, quat) -> ET.Element:
    joint = ET.SubElement(robot, "joint", name=name, type=kind)
    _origin(joint, np.asarray(pos), np.asarray(quat))
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    return joint


def _body_joint(robot: ET.Element, model: mujoco.MjModel, body: int) -> None:
    """The URDF joint from body `body`'s parent: revolute for one hinge at the body origin, else fixed."""
    parent, child = model.body(int(model.body_parentid[body])).name, model.body(body).name
    pos, quat = model.body_pos[body], model.body_quat[body]
    count = int(model.body_jntnum[body])
    if count == 0:
        _joint(robot, f"{parent}_to_{child}", "fixed", parent, child, pos, quat)
        return
    j = int(model.body_jntadr[body])
    if count > 1 or int(model.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_HINGE) or np.any(model.jnt_pos[j] != 0.0):
        raise ValueError(f"body {child!r}: only one hinge at the body origin maps onto a URDF joint")
    joint = _joint(robot, model.joint(j).name, "revolute", parent, child, pos, quat)
    ET.SubElement(joint, "axis", xyz=_vec(model.jnt_axis[j]))
    lower, upper = model.jnt_range[j] if model.jnt_limited[j] else (-np.pi, np.pi)
    ET.SubElement(joint, "limit", lower=_vec([lower]), upper=_vec([upper]), effort="0", velocity="0")


def write_urdf(model: mujoco.MjModel, name: str, out: Path) -> None:
    """URDF `name` of the compiled `model` at `out`, its meshes as STL files in ``<out stem>_meshes/``."""
    mesh_folder = out.parent / f"{out.stem}_meshes"
    mesh_folder.mkdir(exist_ok=True)
    robot = ET.Element("robot", name=name)
    for body in range(model.nbody):
        link = ET.SubElement(robot, "link", name=model.body(body).name)
        _link_geoms(link, model, body, mesh_folder)
        if body > 0:
            _body_joint(robot, model, body)
    for s in range(model.nsite):
        link, parent = f"{model.site(s).name}_frame", model.body(int(model.site_bodyid[s])).name
        ET.SubElement(robot, "link", name=link)
        _joint(robot, f"{parent}_to_{link}", "fixed", parent, link, model.site_pos[s], model.site_quat[s])
    ET.indent(robot)
    out.write_text(ET.tostring(robot, encoding="unicode") + "\n")


def export(fmt: str, out: Path, testbed: bool = False, params: SceneParameters | None = None) -> None:
    """Write the BioTac on its mount (or the testbed) to `out` as `fmt` ("mjcf" or "urdf")."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
    if out.is_dir() or not out.parent.is_dir():
        raise ValueError(f"--out {out}: needs a file name in an existing folder")
    spec = export_spec(params if params is not None else SceneParameters(), testbed)
    if fmt == "mjcf":
        write_mjcf(spec, out)
    else:
        write_urdf(spec.compile(), spec.modelname, out)
