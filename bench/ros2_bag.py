#!/usr/bin/env python3
"""Write ROS 2 bags (MCAP) with an independent writer, Foxglove's Python `mcap-ros2-support`
(its own CDR serialiser, chunks compressed by the zstandard/lz4 C libraries), to check that
headalign reads what other ROS 2 tools write.

usage:
  bench/ros2_bag.py euroc OUT.mcap [--encoding mono8|rgb8|bgr8|mono16|png] [--compression zstd|lz4|none]
      the EuRoC pairs 3 and 2 of data/euroc_v101_pairs as /cam0/image_raw and
      /cam1/image_raw, 0.5 s apart (then: headalign calibrate OUT.mcap --zero-skew
      --square-pixels --lens-from $D/euroc_v101_pairs/cam0_sensor.yaml,$D/euroc_v101_pairs/cam1_sensor.yaml)
  bench/ros2_bag.py session DIR OUT.mcap
      a headalign image session (demo --images --session DIR, run) as the bag `ros2 bag
      record` of that head run would be: three frames per capture, 50 ms apart, and joint
      states `pan`, `tilt`, `vl`, `vr` (radians) at each frame (then: headalign replay
      OUT.mcap --joint pan=pan,elevation=tilt,verge_left=vl,verge_right=vr)
  bench/ros2_bag.py fixture OUT.mcap
      the small bag crates/headalign-io/tests/data/python_mcap_ros2.mcap: three 32x24 mono8
      pairs (pixel = (3 x + 5 y + 17 k + 40 side) mod 256) at t = 10 + 0.1 k s, the right
      0.2 ms later, and joint states at 100 Hz from 9.95 s to 10.35 s, `pan_joint` =
      0.5 (t - 10) rad, `tilt_joint` = -0.1 rad, zstd chunks of 4 KB
needs: pip install mcap-ros2-support zstandard lz4 pillow numpy (for this script only)
"""
import argparse, json, math, os, sys

from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

TIME = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
IMAGE = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n" + TIME
COMPRESSED = "std_msgs/Header header\nstring format\nuint8[] data\n" + TIME
JOINTS = "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n" + TIME


def header(t_ns, frame):
    return {"stamp": {"sec": t_ns // 10**9, "nanosec": t_ns % 10**9}, "frame_id": frame}


def image(t_ns, frame, width, height, encoding, data, big=0):
    step = len(data) // height
    return {"header": header(t_ns, frame), "height": height, "width": width, "encoding": encoding,
            "is_bigendian": big, "step": step, "data": bytes(data)}


def euroc(args):
    import numpy as np
    from PIL import Image as Pil
    data = os.path.join(os.path.dirname(__file__), "../data/euroc_v101_pairs")
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[args.compression]
    with open(args.out, "wb") as f:
        w = Writer(f, compression=comp)
        schema = w.register_msgdef("sensor_msgs/msg/CompressedImage" if args.encoding == "png" else "sensor_msgs/msg/Image",
                                   COMPRESSED if args.encoding == "png" else IMAGE)
        for k, pair in enumerate([3, 2]):
            t = 1_403_715_273_262_142_976 + k * 500_000_000
            for topic, side in [("/cam0/image_raw", "left"), ("/cam1/image_raw", "right")]:
                path = os.path.join(data, f"{side}_img_{pair}.png")
                if args.encoding == "png":
                    msg = {"header": header(t, side), "format": "mono8; png compressed mono8", "data": open(path, "rb").read()}
                else:
                    g = np.asarray(Pil.open(path).convert("L"))
                    h, wd = g.shape
                    if args.encoding == "mono8":
                        pix = g.tobytes()
                    elif args.encoding == "mono16":
                        pix = (g.astype(np.uint16) << 4).astype(">u2").tobytes()  # 12-bit data, big-endian
                    else:
                        pix = np.repeat(g[:, :, None], 3, axis=2).tobytes()  # grey as colour
                    msg = image(t, side, wd, h, args.encoding, pix, big=int(args.encoding == "mono16"))
                w.write_message(topic, schema, msg, log_time=t, publish_time=t)
        w.finish()


def fixture(args):
    with open(args.out, "wb") as f:
        w = Writer(f, chunk_size=4096, compression=CompressionType.ZSTD)
        img = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        js = w.register_msgdef("sensor_msgs/msg/JointState", JOINTS)
        t0 = 10 * 10**9
        for k in range(41):
            t = t0 - 50_000_000 + k * 10_000_000
            msg = {"header": header(t, ""), "name": ["pan_joint", "tilt_joint"],
                   "position": [0.5 * (t - t0) * 1e-9, -0.1], "velocity": [], "effort": []}
            w.write_message("/joint_states", js, msg, log_time=t, publish_time=t)
        for k in range(3):
            for side, (topic, lag) in enumerate([("/left/image_raw", 0), ("/right/image_raw", 200_000)]):
                t = t0 + k * 100_000_000 + lag
                pix = [(3 * x + 5 * y + 17 * k + 40 * side) % 256 for y in range(24) for x in range(32)]
                w.write_message(topic, img, image(t, "cam", 32, 24, "mono8", pix), log_time=t, publish_time=t)
        w.finish()


def session(args):
    import numpy as np
    from PIL import Image as Pil
    folders = sorted(d for d in os.listdir(args.out) if os.path.exists(os.path.join(args.out, d, "view.json")))
    with open(args.bag, "wb") as f:
        w = Writer(f)
        img, js = w.register_msgdef("sensor_msgs/msg/Image", IMAGE), w.register_msgdef("sensor_msgs/msg/JointState", JOINTS)
        for k, folder in enumerate(folders):
            e = json.load(open(os.path.join(args.out, folder, "view.json")))["encoders"]
            pos = [math.radians(e[n]) for n in ["pan", "elevation", "verge_left", "verge_right"]]
            for j in range(3):
                t = 10**12 + k * 10**9 + j * 50_000_000
                w.write_message("/joint_states", js, {"header": header(t, ""), "name": ["pan", "tilt", "vl", "vr"],
                                                      "position": pos, "velocity": [], "effort": []}, log_time=t)
                for topic, side in [("/left/image_raw", "left"), ("/right/image_raw", "right")]:
                    g = np.asarray(Pil.open(os.path.join(args.out, folder, side + ".png")).convert("L"))
                    w.write_message(topic, img, image(t, side, g.shape[1], g.shape[0], "mono8", g.tobytes()), log_time=t)
        w.finish()


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("what", choices=["euroc", "fixture", "session"])
    p.add_argument("out", help="the bag to write (session: the session folder to read)")
    p.add_argument("bag", nargs="?", help="session: the bag to write")
    p.add_argument("--encoding", default="mono8", choices=["mono8", "rgb8", "bgr8", "mono16", "png"])
    p.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"])
    a = p.parse_args()
    {"euroc": euroc, "fixture": fixture, "session": session}[a.what](a)
    print(f"wrote {a.bag or a.out}", file=sys.stderr)
