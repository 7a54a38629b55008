"""Generate fk_reference.json: Franka Panda forward kinematics from two independent libraries.

The independent reference for moonhaul-core's URDF kinematics
(crates/core/tests/kinematics_reference.rs). Reproduce from the repository root with:

    python3 -m venv /tmp/fkvenv
    /tmp/fkvenv/bin/pip install pin==4.1.0 pybullet==3.2.7 numpy
    /tmp/fkvenv/bin/python crates/core/tests/data/gen_fk_fixture.py

The stored poses come from pinocchio (double precision, its own URDF parser). pybullet, whose
pybullet_data package is where panda.urdf comes from, recomputes every pose as a cross-check;
it stores URDF geometry in single precision (origin 0.088 reads back as 0.0879999995), so it is
only required to agree within 1e-6 m / 1e-6 rad. The script refuses to run unless the
pybullet_data URDF is byte-identical to the copy next to it.

Poses are URDF *link frames*: the tip link frame expressed in the base link frame, translation
in metres and unit quaternion (x, y, z, w) with w >= 0. pybullet reports a body's base pose as
its inertial frame, so the base link frame is recovered through the base's local inertial frame.
"""

import hashlib
import importlib.metadata
import json
import os
import random

import numpy as np
import pinocchio as pin
import pybullet as p
import pybullet_data

HERE = os.path.dirname(os.path.abspath(__file__))
OURS = os.path.join(HERE, "panda.urdf")
ARM = [f"panda_joint{i}" for i in range(1, 8)]

# (base link, tip link, movable joints in chain order, i.e. as traversed from base to tip).
CHAINS = [
    ("panda_link0", "panda_grasptarget", ARM),
    ("panda_link0", "panda_leftfinger", ARM + ["panda_finger_joint1"]),
    # Up through finger_joint1 (inverse traversal), then down through finger_joint2.
    ("panda_leftfinger", "panda_rightfinger", ["panda_finger_joint1", "panda_finger_joint2"]),
    # Entirely upward: the tip is an ancestor of the base.
    ("panda_hand", "panda_link3", ["panda_joint7", "panda_joint6", "panda_joint5", "panda_joint4"]),
]
TOLERANCE = 1e-6


def sha256(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


class Pinocchio:
    def __init__(self, urdf):
        self.model = pin.buildModelFromUrdf(urdf)
        self.data = self.model.createData()

    def limits(self, joint):
        idx = self.model.joints[self.model.getJointId(joint)].idx_q
        return self.model.lowerPositionLimit[idx], self.model.upperPositionLimit[idx]

    def pose(self, base, tip, joints, q):
        """Returns (translation, rotation matrix) of tip in base."""
        config = pin.neutral(self.model)
        for name, value in zip(joints, q):
            joint = self.model.joints[self.model.getJointId(name)]
            assert joint.nq == 1, f"{name}: only 1-DOF joints are handled"
            config[joint.idx_q] = value
        pin.framesForwardKinematics(self.model, self.data, config)
        frame = lambda link: self.data.oMf[self.model.getFrameId(link, pin.FrameType.BODY)]
        pose = frame(base).inverse() * frame(tip)
        return pose.translation, pose.rotation


class PyBullet:
    def __init__(self, urdf):
        p.connect(p.DIRECT)
        self.body = p.loadURDF(urdf, useFixedBase=True)
        self.joint_index, self.link_index = {}, {p.getBodyInfo(self.body)[0].decode(): -1}
        for j in range(p.getNumJoints(self.body)):
            info = p.getJointInfo(self.body, j)
            self.joint_index[info[1].decode()] = j
            self.link_index[info[12].decode()] = j

    def link_frame(self, link):
        if self.link_index[link] == -1:
            com = p.getBasePositionAndOrientation(self.body)
            local_com = p.getDynamicsInfo(self.body, -1)[3:5]
            return p.multiplyTransforms(*com, *p.invertTransform(*local_com))
        return p.getLinkState(self.body, self.link_index[link], computeForwardKinematics=True)[4:6]

    def pose(self, base, tip, joints, q):
        for j in range(p.getNumJoints(self.body)):
            p.resetJointState(self.body, j, 0.0)
        for name, value in zip(joints, q):
            p.resetJointState(self.body, self.joint_index[name], value)
        pos, orn = p.multiplyTransforms(*p.invertTransform(*self.link_frame(base)), *self.link_frame(tip))
        return np.array(pos), np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)


def main():
    original = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
    # Ours is the original with the massless frame links' placeholder inertia zeroed (README).
    with open(original) as f:
        expected = f.read().replace(
            '<inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/>\n    </inertial>\n  </link>\n  <joint name="panda_joint8"',
            '<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>\n    </inertial>\n  </link>\n  <joint name="panda_joint8"',
        ).replace(
            '<inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/>\n    </inertial>\n   </link>\n   <joint name="panda_grasptarget_hand"',
            '<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>\n    </inertial>\n   </link>\n   <joint name="panda_grasptarget_hand"',
        )
    with open(OURS) as f:
        if f.read() != expected:
            raise SystemExit(f"{OURS} is not {original} with the README's one change")
    reference, cross_check = Pinocchio(OURS), PyBullet(original)

    rng = random.Random(20240611)
    chains = []
    for base, tip, joints in CHAINS:
        lower, upper = zip(*(reference.limits(j) for j in joints))
        qs = [[0.0] * len(joints)]
        if (base, tip) == ("panda_link0", "panda_grasptarget"):
            qs += [
                [0.3, -0.5, 0.7, -1.2, 0.4, 1.1, -0.6],
                list(lower),
                list(upper),
                [-0.5, 1.2, -2.0, -0.1, -2.5, 0.0, 2.9],
                [-2.9, -1.8, 2.9, -3.0, 2.9, 3.8, -2.9],
            ]
        qs += [[rng.uniform(lo, hi) for lo, hi in zip(lower, upper)] for _ in range(6)]

        configs = []
        for q in qs:
            translation, rotation = reference.pose(base, tip, joints, q)
            other_translation, other_rotation = cross_check.pose(base, tip, joints, q)
            assert np.linalg.norm(translation - other_translation) < TOLERANCE, (base, tip, q)
            assert np.linalg.norm(pin.log3(rotation.T @ other_rotation)) < TOLERANCE, (base, tip, q)
            quat = pin.Quaternion(rotation).normalized()
            xyzw = [quat.x, quat.y, quat.z, quat.w]
            if quat.w < 0:
                xyzw = [-c for c in xyzw]
            configs.append({"q": q, "translation": translation.tolist(), "rotation_xyzw": xyzw})
        chains.append({"base": base, "tip": tip, "joints": joints, "configs": configs})

    versions = {name: importlib.metadata.version(name) for name in ("pin", "pybullet")}
    fixture = {
        "generator": "gen_fk_fixture.py",
        "reference": f"pinocchio (PyPI pin {versions['pin']}): framesForwardKinematics, BODY frames",
        "cross_check": f"pybullet {versions['pybullet']} (PyPI), agrees within {TOLERANCE}",
        "urdf": "panda.urdf",
        "urdf_sha256": sha256(OURS),
        "chains": chains,
    }
    with open(os.path.join(HERE, "fk_reference.json"), "w") as f:
        json.dump(fixture, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
