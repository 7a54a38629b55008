"""A bare zenoh peer (PyPI eclipse-zenoh, not moonhaul's code) listening where a unit started
with `--ros2-connect` dials, that checks what arrives against rmw_zenoh's wire format and
rosbags' Jazzy type store and CDR codec.

usage: listen_live.py ENDPOINT NAMESPACE SECONDS

Prints `ready` once listening, then after SECONDS (or as soon as it has seen 20 joint states
and the tokens) one line per check; exits non-zero at the first failure.
"""

import struct
import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore


def fail(why):
    print(f"FAIL: {why}", flush=True)
    sys.exit(1)


def main():
    endpoint, ns, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
    store = get_typestore(Stores.ROS2_JAZZY)
    js_hash = store.hash_rihs01("sensor_msgs/msg/JointState")
    js_key = f"0/{ns}/joint_states/sensor_msgs::msg::dds_::JointState_/{js_hash}"

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)

    lock = threading.Lock()
    samples = {}  # key -> [(payload bytes, attachment bytes)]
    tokens = set()

    def on_sample(sample):
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with lock:
            samples.setdefault(str(sample.key_expr), []).append((sample.payload.to_bytes(), att))

    def on_token(sample):
        with lock:
            tokens.add(str(sample.key_expr))

    session.declare_subscriber("0/**", on_sample)
    session.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)
    print("ready", flush=True)

    deadline = time.time() + seconds
    while time.time() < deadline:
        time.sleep(0.2)
        with lock:
            if len(samples.get(js_key, [])) >= 20 and any("/MP/" in t for t in tokens):
                break
    with lock:
        got = dict(samples)
        toks = set(tokens)
    session.close()

    print(f"keys: {sorted(got)}")
    js = got.get(js_key)
    if not js:
        fail(f"no sample on {js_key}")
    seqs = []
    for payload, att in js:
        msg = store.deserialize_cdr(payload, "sensor_msgs/msg/JointState")
        if len(msg.name) != 9 or len(msg.position) != 9 or len(msg.velocity) != 9:
            fail(f"joint state of {len(msg.name)} joints")
        if att is None or len(att) != 33 or att[16] != 16:
            fail(f"attachment {att!r} is not seq (8), timestamp (8), gid length 16, gid (16)")
        seq, source_ns = struct.unpack_from("<qq", att)
        seqs.append(seq)
        if abs(source_ns / 1e9 - time.time()) > 60:
            fail(f"source timestamp {source_ns} ns is not the wall clock")
    if seqs != sorted(seqs) or len(set(seqs)) != len(seqs) or seqs[0] < 1:
        fail(f"sequence numbers {seqs[:5]}... do not increase")
    gids = {att[17:] for _, att in js}
    if len(gids) != 1:
        fail("the publisher GID changes")
    print(f"{js_key}: {len(js)} JointState samples of nine joints ({list(msg.name)}), attachments ok")

    tf_key = f"0/tf/tf2_msgs::msg::dds_::TFMessage_/{store.hash_rihs01('tf2_msgs/msg/TFMessage')}"
    diag_key = f"0/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/{store.hash_rihs01('diagnostic_msgs/msg/DiagnosticArray')}"
    desc_key = f"0/{ns}/robot_description/std_msgs::msg::dds_::String_/{store.hash_rihs01('std_msgs/msg/String')}"
    for key, typ in [(tf_key, "tf2_msgs/msg/TFMessage"), (diag_key, "diagnostic_msgs/msg/DiagnosticArray"), (desc_key, "std_msgs/msg/String")]:
        if not got.get(key):
            fail(f"no sample on {key}")
        store.deserialize_cdr(got[key][-1][0], typ)
    print("tf, diagnostics and robot_description decode: ok")

    node = [t for t in toks if t.split("/")[5:6] == ["NN"]]
    pubs = [t for t in toks if t.split("/")[5:6] == ["MP"]]
    print(f"tokens: {sorted(toks)}")
    if not any(t.endswith(f"/%{ns}/moonhaul_unit") for t in node):
        fail("no node liveliness token")
    want = f"/MP/%/%{ns}/moonhaul_unit/%{ns}%joint_states/sensor_msgs::msg::dds_::JointState_/{js_hash}/"
    if not any(want in t for t in pubs):
        fail(f"no publisher token with {want}")
    if len(pubs) != 5:
        fail(f"{len(pubs)} publisher tokens, expected 5")
    print("liveliness tokens: ok")
    print("live ok", flush=True)


if __name__ == "__main__":
    main()
