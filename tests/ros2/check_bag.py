"""Reads a bag written by `moonhaul log ros2` with rosbags (pure-Python rosbag2 reader and CDR
codec with the ROS 2 Jazzy type store; not moonhaul's code) and checks it against what the
mission logs hold.

usage: check_bag.py BAG EXPECTED.json

EXPECTED.json (written by tests/ros2_cli.rs from moonhaul's own log reader):
  {"units": {"unit_0": [stamp_us, ...], ...},   # every tick's stamp, in order
   "payload": [[stamp_us, x, y, z], ...]}         # every ground-truth frame

Prints one line per check and exits non-zero at the first failure.
"""

import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore


def fail(why):
    print(f"FAIL: {why}")
    sys.exit(1)


def check(cond, why):
    if not cond:
        fail(why)


def stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def main():
    bag, expected_path = Path(sys.argv[1]), Path(sys.argv[2])
    expected = json.loads(expected_path.read_text())
    store = get_typestore(Stores.ROS2_JAZZY)

    with Reader(bag) as reader:
        conns = {c.topic: c for c in reader.connections}
        print(f"topics: {sorted(conns)}")
        for c in reader.connections:
            # The type hash: what rosbags computes for Jazzy's definition of the type.
            check(
                c.digest == store.hash_rihs01(c.msgtype),
                f"{c.topic}: type hash {c.digest} is not Jazzy's {store.hash_rihs01(c.msgtype)}",
            )
            # The schema stored in the bag parses to exactly Jazzy's fields, nested types too.
            types = get_types_from_msg(c.msgdef.data, c.msgtype)
            for name, fields in types.items():
                check(fields == store.fielddefs[name], f"{c.topic}: schema of {name} differs from Jazzy's")
            check(c.ext.serialization_format == "cdr", f"{c.topic}: not cdr")
            check(len(c.ext.offered_qos_profiles) == 1, f"{c.topic}: no offered QoS")
        print("type hashes, schemas, cdr and QoS of every topic: ok")

        wanted = ["/tf", "/tf_static", "/diagnostics"]
        for ns in expected["units"]:
            wanted += [f"/{ns}/joint_states", f"/{ns}/robot_description"]
        if expected["payload"]:
            wanted.append("/ground_truth/payload")
        check(sorted(wanted) == sorted(conns), f"topics {sorted(conns)}, expected {sorted(wanted)}")
        durability = {t: conns[t].ext.offered_qos_profiles[0].durability.name for t in conns}
        for t in conns:
            latched = t == "/tf_static" or t.endswith("/robot_description")
            check(
                durability[t] == ("TRANSIENT_LOCAL" if latched else "VOLATILE"),
                f"{t}: durability {durability[t]}",
            )

        joints = {ns: [] for ns in expected["units"]}
        tf = {ns: [] for ns in expected["units"]}
        diag = {ns: [] for ns in expected["units"]}
        descriptions, tf_static, payload = {}, [], []
        for conn, t_ns, raw in reader.messages():
            msg = store.deserialize_cdr(raw, conn.msgtype)
            topic = conn.topic
            if topic.endswith("/joint_states"):
                joints[topic.split("/")[1]].append((t_ns, msg))
            elif topic.endswith("/robot_description"):
                descriptions[topic.split("/")[1]] = msg.data
            elif topic == "/tf":
                ns = msg.transforms[0].header.frame_id.split("/")[0]
                tf[ns].append((t_ns, msg))
            elif topic == "/tf_static":
                tf_static.append(msg)
            elif topic == "/diagnostics":
                diag[msg.status[0].hardware_id].append((t_ns, msg))
            elif topic == "/ground_truth/payload":
                payload.append((t_ns, msg))

    check(len(tf_static) == 1, f"{len(tf_static)} /tf_static messages, expected one for all units")
    static_edges = {(x.header.frame_id, x.child_frame_id) for x in tf_static[0].transforms}
    for ns, stamps in expected["units"].items():
        urdf = ET.fromstring(descriptions[ns])
        movable = [j for j in urdf.findall("joint") if j.get("type") != "fixed"]
        fixed = [j for j in urdf.findall("joint") if j.get("type") == "fixed"]
        names = [j.get("name") for j in movable]
        check(len(names) == 9, f"{ns}: the URDF has {len(names)} movable joints, not nine")

        # One joint_states per tick, stamped with the tick's stamp, logged at it.
        js = joints[ns]
        check(len(js) == len(stamps), f"{ns}: {len(js)} joint_states for {len(stamps)} ticks")
        for (t_ns, msg), us in zip(js, stamps):
            check(stamp_ns(msg.header) == us * 1000 == t_ns, f"{ns}: joint_states stamp {stamp_ns(msg.header)} / log time {t_ns}, tick at {us} us")
            check(list(msg.name) == names, f"{ns}: joint names {list(msg.name)}, URDF {names}")
            check(len(msg.position) == 9 and len(msg.velocity) == 9, f"{ns}: not nine positions and velocities")
        print(f"{ns}: {len(js)} joint_states, one per tick, stamped as the ticks, joints {names}: ok")

        # /tf: odom -> base, then each movable joint's child link, all prefixed.
        check(len(tf[ns]) == len(stamps), f"{ns}: {len(tf[ns])} /tf messages for {len(stamps)} ticks")
        base = urdf.find("link").get("name")
        want = {(f"{ns}/odom", f"{ns}/{base}")} | {
            (f"{ns}/{j.find('parent').get('link')}", f"{ns}/{j.find('child').get('link')}") for j in movable
        }
        for t_ns, msg in tf[ns]:
            edges = {(x.header.frame_id, x.child_frame_id) for x in msg.transforms}
            check(edges == want, f"{ns}: /tf edges {sorted(edges)}, expected {sorted(want)}")
            check(all(stamp_ns(x.header) == t_ns for x in msg.transforms), f"{ns}: /tf stamps")
        want_static = {("world", f"{ns}/odom")} | {
            (f"{ns}/{j.find('parent').get('link')}", f"{ns}/{j.find('child').get('link')}") for j in fixed
        }
        check(want_static <= static_edges, f"{ns}: /tf_static lacks {sorted(want_static - static_edges)}")
        print(f"{ns}: /tf ({len(want)} edges per tick) and /tf_static: ok")

        # /diagnostics: one status per tick, phase and the clamp's figures by name.
        check(len(diag[ns]) == len(stamps), f"{ns}: {len(diag[ns])} diagnostics for {len(stamps)} ticks")
        phases = []
        for _, msg in diag[ns]:
            values = {kv.key: kv.value for kv in msg.status[0].values}
            for key in ("phase", "t_max", "hold", "fault"):
                check(key in values, f"{ns}: diagnostics without {key}")
            check(0.0 <= float(values["t_max"]) <= 1.0, f"{ns}: t_max {values['t_max']}")
            check(any(k.startswith("peer_age_s.") for k in values), f"{ns}: no peer ages")
            if not phases or phases[-1] != values["phase"]:
                phases.append(values["phase"])
        check(
            [p for p in phases if p != "idle"][:3] == ["lift", "transport", "place"],
            f"{ns}: phases {phases}",
        )
        print(f"{ns}: diagnostics, phases {phases}: ok")

    want = expected["payload"]
    check(len(payload) == len(want), f"{len(payload)} ground-truth poses for {len(want)} frames")
    for (t_ns, msg), (us, x, y, z) in zip(payload, want):
        p = msg.pose.position
        check(stamp_ns(msg.header) == us * 1000 == t_ns, f"ground truth stamp {t_ns} vs {us} us")
        check((p.x, p.y, p.z) == (x, y, z), f"ground truth at {us} us: {(p.x, p.y, p.z)} vs {(x, y, z)}")
        check(msg.header.frame_id == "world", "ground truth frame")
    print(f"/ground_truth/payload: {len(payload)} poses as the world log's: ok")
    print("bag ok")


if __name__ == "__main__":
    main()
