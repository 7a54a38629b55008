#!/usr/bin/env python3
"""Writes the moonhaul robot and payload URDFs in this folder from one parameter table.

Run `python3 assets/gen_urdf.py` after changing a number; the .urdf files are generated and
committed so that nothing at runtime needs Python.

Arm reference: KUKA LBR iiwa 14 R820 (rated payload 14 kg, so two arms sharing the 9.5 kg
bricks payload stay well inside their rating). Kinematics, link masses, centres of mass and
inertias follow the community iiwa14 description (iiwa_stack / kuka-isir `iiwa14.xacro`);
effort and velocity limits are KUKA's datasheet values (320, 320, 176, 176, 110, 40, 40 N m;
85, 85, 100, 75, 130, 135, 135 deg/s), position limits ±170/120/170/120/170/120/175 deg. Changes: link names, a
rigid paddle end effector (0.6 kg) whose frame `ee` is the grasp point 0.145 m beyond the
flange, `<dynamics damping>` added, and no meshes (the simulator uses no arm collision).
"""
import math
import os

HERE = os.path.dirname(os.path.abspath(__file__))
PI = math.pi

# ---- wheel module -------------------------------------------------------------------------
WHEEL_RADIUS = 0.10
WHEEL_WIDTH = 0.05
WHEEL_MASS = 1.5
WHEEL_Y = 0.28  # half track
WHEEL_EFFORT = 40.0  # N m
WHEEL_VELOCITY = 10.0  # rad/s (1 m/s)
CHASSIS = (0.60, 0.50, 0.15)  # box, m
CHASSIS_MASS = 40.0  # frame, batteries and drives
CHASSIS_Z = 0.05  # box centre above the axle
CASTER_RADIUS = 0.05
CASTER_X = 0.25
CASTER_MASS = 0.3
# The casters float this far above level ground: the driven wheels carry the weight (a
# four-point stance would let the casters take it and the wheels slip) and a caster only
# touches down when the base pitches. The gap exceeds the terrain perturbation (0.02 m peak to
# peak) seen between wheel and caster, or a caster riding a bump lifts the outer wheel.
CASTER_GAP = 0.015
# Arm base on the chassis top, set back from the side the arm reaches toward (+Y) so that the
# arm and its share of the payload do not unload the far wheel.
MOUNT = (0.0, -0.15, CHASSIS_Z + CHASSIS[2] / 2)

# ---- arm module: KUKA LBR iiwa 14 R820 ----------------------------------------------------
# (origin xyz, origin rpy, lower/upper rad, effort N m, velocity rad/s, child mass, com, diag I)
ARM_BASE = dict(mass=5.0, com=(-0.1, 0.0, 0.07), inertia=(0.05, 0.06, 0.03))
ARM_JOINTS = [
    ((0, 0, 0.1575), (0, 0, 0), 170, 320, 85, 4.0, (0, -0.03, 0.12), (0.1, 0.09, 0.02)),
    ((0, 0, 0.2025), (PI / 2, 0, PI), 120, 320, 85, 4.0, (0.0003, 0.059, 0.042), (0.05, 0.018, 0.044)),
    ((0, 0.2045, 0), (PI / 2, 0, PI), 170, 176, 100, 3.0, (0, 0.03, 0.13), (0.08, 0.075, 0.01)),
    ((0, 0, 0.2155), (PI / 2, 0, 0), 120, 176, 75, 2.7, (0, 0.067, 0.034), (0.03, 0.01, 0.029)),
    ((0, 0.1845, 0), (-PI / 2, PI, 0), 170, 110, 130, 1.7, (0.0001, 0.021, 0.076), (0.02, 0.018, 0.005)),
    ((0, 0, 0.2155), (PI / 2, 0, 0), 120, 40, 135, 1.8, (0, 0.0006, 0.0004), (0.005, 0.0036, 0.0047)),
    ((0, 0.081, 0), (-PI / 2, PI, 0), 175, 40, 135, 0.3, (0, 0, 0.02), (0.001, 0.001, 0.001)),
]
ARM_JOINT_DAMPING = 0.5  # N m s/rad, viscous
EE_OFFSET = 0.045 + 0.10  # flange + paddle, along link 7's z
EE_MASS = 0.6

# ---- payloads: (name, size xyz m, mass kg, com offset m) ----------------------------------
PAYLOADS = [
    ("box", (0.40, 0.30, 0.30), 7.5, (0, 0, 0)),
    # The same box with bricks on its floor: heavier and bottom-heavy.
    ("bricks", (0.40, 0.30, 0.30), 9.5, (0, 0, -0.05)),
    # Elongated along the travel direction and flat: the paper's unseen shape.
    ("sledge", (1.00, 0.30, 0.12), 5.3, (0, 0, 0)),
]


def f(v):
    return " ".join(f"{x:.6g}" for x in v)


def inertial(mass, com, diag):
    return (f'    <inertial>\n      <origin xyz="{f(com)}" rpy="0 0 0"/>\n'
            f'      <mass value="{mass:.6g}"/>\n'
            f'      <inertia ixx="{diag[0]:.6g}" ixy="0" ixz="0" iyy="{diag[1]:.6g}" iyz="0" izz="{diag[2]:.6g}"/>\n'
            f'    </inertial>\n')


def box_inertia(mass, size):
    x, y, z = size
    return (mass * (y * y + z * z) / 12, mass * (x * x + z * z) / 12, mass * (x * x + y * y) / 12)


def link(name, body="", collision=""):
    return f'  <link name="{name}">\n{body}{collision}  </link>\n'


def joint(name, kind, parent, child, xyz, rpy=(0, 0, 0), axis=None, limit=None, damping=None):
    s = f'  <joint name="{name}" type="{kind}">\n    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
    s += f'    <origin xyz="{f(xyz)}" rpy="{f(rpy)}"/>\n'
    if axis:
        s += f'    <axis xyz="{f(axis)}"/>\n'
    if limit:
        s += f'    <limit lower="{limit[0]:.6g}" upper="{limit[1]:.6g}" effort="{limit[2]:.6g}" velocity="{limit[3]:.6g}"/>\n'
    if damping is not None:
        s += f'    <dynamics damping="{damping:.6g}" friction="0"/>\n'
    return s + "  </joint>\n"


def sphere(r):
    return f'    <collision>\n      <geometry><sphere radius="{r:.6g}"/></geometry>\n    </collision>\n'


def wheel_module(prefix=""):
    """The differential-drive base: chassis, two driven wheels, front and rear caster balls."""
    cyl_i = (WHEEL_MASS * (3 * WHEEL_RADIUS**2 + WHEEL_WIDTH**2) / 12, WHEEL_MASS * WHEEL_RADIUS**2 / 2,
             WHEEL_MASS * (3 * WHEEL_RADIUS**2 + WHEEL_WIDTH**2) / 12)
    s = link("base_link", inertial(CHASSIS_MASS, (0, 0, CHASSIS_Z), box_inertia(CHASSIS_MASS, CHASSIS)))
    for side, y in (("left", WHEEL_Y), ("right", -WHEEL_Y)):
        # Contact is a sphere of the wheel radius: same rolling contact point, robust on a
        # heightfield; the lateral friction it gets is what makes the base nonholonomic.
        s += link(f"wheel_{side}", inertial(WHEEL_MASS, (0, 0, 0), cyl_i), sphere(WHEEL_RADIUS))
        s += joint(f"wheel_{side}_joint", "continuous", "base_link", f"wheel_{side}", (0, y, 0),
                   axis=(0, 1, 0), limit=(0, 0, WHEEL_EFFORT, WHEEL_VELOCITY), damping=0.0)
    for side, x in (("front", CASTER_X), ("rear", -CASTER_X)):
        ci = 2 / 5 * CASTER_MASS * CASTER_RADIUS**2
        s += link(f"caster_{side}", inertial(CASTER_MASS, (0, 0, 0), (ci, ci, ci)), sphere(CASTER_RADIUS))
        s += joint(f"caster_{side}_joint", "fixed", "base_link", f"caster_{side}",
                   (x, 0, CASTER_RADIUS - WHEEL_RADIUS + CASTER_GAP))
    return s


def arm_module(parent=None, mount=(0, 0, 0)):
    """The 7-DOF arm; attached to `parent` by a fixed joint when given."""
    s = link("arm_link_0", inertial(ARM_BASE["mass"], ARM_BASE["com"], ARM_BASE["inertia"]))
    if parent:
        s += joint("arm_mount", "fixed", parent, "arm_link_0", mount)
    prev = "arm_link_0"
    for i, (xyz, rpy, lim, eff, vel, m, com, diag) in enumerate(ARM_JOINTS, start=1):
        s += link(f"arm_link_{i}", inertial(m, com, diag))
        s += joint(f"arm_joint_{i}", "revolute", prev, f"arm_link_{i}", xyz, rpy, axis=(0, 0, 1),
                   limit=(-math.radians(lim), math.radians(lim), eff, math.radians(vel)),
                   damping=ARM_JOINT_DAMPING)
        prev = f"arm_link_{i}"
    # Paddle end effector: its frame is the grasp point, z along the approach direction.
    ee_i = (0.002, 0.002, 0.001)
    s += link("ee", inertial(EE_MASS, (0, 0, -0.07), ee_i))
    s += joint("ee_joint", "fixed", prev, "ee", (0, 0, EE_OFFSET))
    return s


def robot(name, body):
    return f'<?xml version="1.0"?>\n<!-- Generated by assets/gen_urdf.py; edit that instead. -->\n<robot name="{name}">\n{body}</robot>\n'


def payload(name, size, mass, com):
    body = inertial(mass, com, box_inertia(mass, size))
    col = f'    <collision>\n      <geometry><box size="{f(size)}"/></geometry>\n    </collision>\n'
    return robot(f"payload_{name}", link("payload", body, col))


def main():
    files = {
        "wheel_module.urdf": robot("wheel_module", wheel_module()),
        "arm_module.urdf": robot("arm_module", arm_module()),
        "unit.urdf": robot("wheel_arm_unit", wheel_module() + arm_module("base_link", MOUNT)),
    }
    for name, size, mass, com in PAYLOADS:
        files[f"payload_{name}.urdf"] = payload(name, size, mass, com)
    for fname, text in files.items():
        with open(os.path.join(HERE, fname), "w") as fh:
            fh.write(text)


if __name__ == "__main__":
    main()
