"""A collision reference outside the planner, for the planning tests (a helper module, not a test
module): Pinocchio parses the URDF, computes the forward kinematics and places the collision
geometry; trimesh loads the meshes; python-fcl measures the distances; the cell's obstacles sit
where the scene puts them, the robot's root at ``T_cell_root`` in the cell. Which link pairs to
check is the planner's choice (:meth:`FclReference.pairs`), where they are is not."""

from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from campaign.plan.scene import load_scene


def erd_share() -> Path:
    """The ``share`` folder of the test extra example-robot-data (skips when it is not installed)."""
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    return Path(dist.locate_file("cmeel.prefix/share"))


def erd_robot(rel) -> Path:
    """A file of example-robot-data's robots, e.g. ``ur_description/urdf/ur10_robot.urdf``."""
    return erd_share() / "example-robot-data" / "robots" / rel


class FclReference:
    """The robot's URDF collision geometry (boxes, cylinders, meshes) and the cell's obstacles as
    python-fcl objects, placed by Pinocchio at a joint vector (:meth:`place`)."""

    def __init__(self, robot, scene_path, T_cell_root):
        import fcl
        import pinocchio as pin
        import trimesh

        self.robot, self.pin, self.fcl = robot, pin, fcl
        self.T_cell_root = np.asarray(T_cell_root, dtype=float)
        self.model = pin.buildModelFromUrdf(str(robot.urdf_path))
        self.data = self.model.createData()
        dirs = [str(erd_share())] if "example-robot-data" in str(robot.urdf_path) else []
        self.gmodel = pin.buildGeomFromUrdf(self.model, str(robot.urdf_path), pin.COLLISION, package_dirs=dirs)
        self.gdata = pin.GeometryData(self.gmodel)
        self.objs, self.links, self.joint = [], [], []
        for g in self.gmodel.geometryObjects:
            kind = type(g.geometry).__name__
            if kind == "Box":
                shape = fcl.Box(*(2 * np.asarray(g.geometry.halfSide)))
            elif kind == "Cylinder":
                shape = fcl.Cylinder(g.geometry.radius, 2 * g.geometry.halfLength)
            elif kind == "Sphere":
                shape = fcl.Sphere(g.geometry.radius)
            elif kind == "Capsule":
                shape = fcl.Capsule(g.geometry.radius, 2 * g.geometry.halfLength)
            else:
                m = trimesh.load(g.meshPath, force="mesh")
                shape = fcl.BVHModel()
                v = np.asarray(m.vertices) * np.asarray(g.meshScale)
                shape.beginModel(len(v), len(m.faces))
                shape.addSubModel(v, np.asarray(m.faces, dtype=np.int32))
                shape.endModel()
            self.objs.append(fcl.CollisionObject(shape, fcl.Transform()))
            self.links.append(self.model.frames[g.parentFrame].name)
            self.joint.append(g.parentJoint)
        self.scene = load_scene(scene_path)  # in the cell's frame, not placed
        self.obstacles = [fcl.CollisionObject(fcl.Box(*o.size) if o.kind == "box" else fcl.Cylinder(*o.size),
                                              fcl.Transform(o.T_I[:3, :3], o.T_I[:3, 3])) for o in self.scene.obstacles]
        self.names = [o.name for o in self.scene.obstacles]

    def index_of(self, prims) -> list:
        """For each planner primitive, the index of the same <collision> among Pinocchio's geometry
        objects (the n-th collision of a link in URDF order, both sides)."""
        by_link, seen, out = {}, {}, []
        for n, link in enumerate(self.links):
            by_link.setdefault(link, []).append(n)
        for p in prims:
            out.append(by_link[p.link][seen.get(p.link, 0)])
            seen[p.link] = seen.get(p.link, 0) + 1
        return out

    def pairs(self, checker) -> list:
        """The link pairs the planner's ``checker`` checks (all but adjacent links and pairs always
        in contact), as pairs of Pinocchio's geometry objects."""
        index = self.index_of(checker.prims)
        return [(index[i], index[k]) for i, k in checker.self_pairs]

    def place(self, q):
        """Put the geometry at joint vector q (N,) (other joints at robot.yaml's locked values, else
        0); returns the tool frame's pose (4, 4) in the cell."""
        qp = self.pin.neutral(self.model)
        for jid in range(1, self.model.njoints):
            name = self.model.names[jid]
            v = q[self.robot.joint_names.index(name)] if name in self.robot.joint_names else \
                self.robot.locked_joints.get(name, 0.0)
            qp[self.model.joints[jid].idx_q] = v
        self.pin.framesForwardKinematics(self.model, self.data, qp)
        self.pin.updateGeometryPlacements(self.model, self.data, self.gmodel, self.gdata, qp)
        for obj, M in zip(self.objs, self.gdata.oMg):
            T = self.T_cell_root @ M.homogeneous
            obj.setTransform(self.fcl.Transform(T[:3, :3], T[:3, 3]))
        return self.T_cell_root @ self.data.oMf[self.model.getFrameId(self.robot.tool_frame, self.pin.BODY)].homogeneous

    def dist(self, a, b) -> float:
        return self.fcl.distance(a, b, self.fcl.DistanceRequest(), self.fcl.DistanceResult())

    def min_clearance(self, q, pairs=()) -> float:
        """Smallest distance (m) at joint vector q: every moving link to every obstacle, and the
        link pairs given (:meth:`pairs`)."""
        self.place(q)
        d = [self.dist(o, s) for o, j in zip(self.objs, self.joint) if j >= 1 for s in self.obstacles]
        d += [self.dist(self.objs[i], self.objs[k]) for i, k in pairs]
        return min(d)

    def link_to(self, q, link_index, obstacle) -> float:
        """Distance (m) at q from geometry object ``link_index`` to the obstacle named ``obstacle``."""
        self.place(q)
        return self.dist(self.objs[link_index], self.obstacles[self.names.index(obstacle)])

    def visible(self, q, reflectors) -> bool:
        """Every reflector within range, inside its nest's cone, and its beam (a capsule of the beam
        radius) clear of the cell and of the links before the last joint."""
        T = self.place(q)
        o = self.scene.tracker_position
        N = self.robot.n_joints
        for r in reflectors:
            p = T[:3, :3] @ r.position_in_E + T[:3, 3]
            axis = T[:3, :3] @ r.axis_in_E
            to = o - p
            d = np.linalg.norm(to)
            if not self.scene.min_range_m <= d <= self.scene.max_range_m:
                return False
            if np.arccos(np.clip(axis @ to / d, -1, 1)) > r.half_angle:
                return False
            z = to / d
            x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
            x /= np.linalg.norm(x)
            beam = self.fcl.CollisionObject(self.fcl.Capsule(self.scene.beam_radius_m, d),
                                            self.fcl.Transform(np.stack([x, np.cross(z, x), z], axis=1), p + 0.5 * to))
            others = self.obstacles + [ob for ob, j in zip(self.objs, self.joint) if j < N]
            if any(self.dist(beam, other) <= 0.0 for other in others):
                return False
        return True
