"""`vmocap play BAG`: publish a rosbag2 MCAP's topics (CDR bytes as recorded) with /clock.

--rate scales time (0: as fast as possible), --loop restarts at the end, --start-offset skips
seconds, --restamp shifts every header stamp (and /clock) so the recording reads as happening
now (what the latency benchmark needs: capture stamp = publish time of the first message of
the frame set). With --expect TOPIC..., the player first waits (--wait-subscribers seconds at
most) until those topics have subscribers, so a freshly launched graph misses nothing.
"""

from __future__ import annotations

import argparse
import struct
import sys
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag2 MCAP file")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (0: as fast as possible)")
    parser.add_argument("--loop", action="store_true", help="restart at the end")
    parser.add_argument("--start-offset", type=float, default=0.0, help="skip this many seconds from the start")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many bag seconds (0: all)")
    parser.add_argument("--topics", nargs="+", default=None, help="publish only these topics")
    parser.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    parser.add_argument("--restamp", action="store_true", help="shift header stamps to the wall clock")
    parser.add_argument("--wait-subscribers", type=float, default=3.0, metavar="S",
                        help="wait up to S seconds for subscribers of the topics before playing")
    parser.add_argument("--expect", nargs="+", default=None, metavar="TOPIC",
                        help="wait (up to --wait-subscribers) until these topics have a subscriber")
    parser.add_argument("--start-at", type=float, default=0.0, metavar="UNIX_TIME",
                        help="after the subscriber wait, start playing at this wall-clock time (seconds since the "
                             "epoch): players of one recording's cameras started apart then play in step")
    parser.add_argument("--recover", action="store_true", help="play a truncated bag up to the damage")
    parser.add_argument("--quiet", action="store_true")


def _has_header(type_name: str) -> bool:
    from vmocap_core.bag import cdr

    try:
        f = cdr.fields_of(type_name)
    except Exception:  # noqa: BLE001 - unknown type: never restamp it
        return False
    return bool(f) and f[0].base == "std_msgs/msg/Header" and f[0].array is None


def _shift(data: bytes, offset_ns: int) -> bytes:
    """Add offset_ns to the header stamp (int32 sec, uint32 nanosec right after the 4-byte
    encapsulation header)."""
    sec, nsec = struct.unpack_from("<iI", data, 4)
    t = sec * 1_000_000_000 + nsec + offset_ns
    return data[:4] + struct.pack("<iI", t // 1_000_000_000, t % 1_000_000_000) + data[12:]


def play(args: argparse.Namespace, stop=None) -> dict:
    from vmocap_core.bag import BagReader, cdr
    from vmocap_core.bag import messages as M

    from .common import StopFlag, init_rclpy, msg_class, qos

    stop = stop or StopFlag().install()
    reader = BagReader(args.bag, recover=args.recover).open()
    topics = args.topics or sorted(reader.topics)
    unknown = [t for t in topics if t not in reader.topics]
    if unknown:
        raise SystemExit(f"vmocap play: {args.bag} has no topics {unknown}")
    rclpy = init_rclpy()
    node = rclpy.create_node("vmocap_player")
    pubs = {t: node.create_publisher(msg_class(reader.topics[t]), t, qos(10)) for t in topics}
    restamp = {t: args.restamp and _has_header(reader.topics[t]) for t in topics}
    clock = None if args.no_clock else node.create_publisher(msg_class("rosgraph_msgs/msg/Clock"), "/clock", qos(10))
    counts = {"messages": 0, "loops": 0, "wait_s": 0.0, "publish_s": 0.0, "play_s": 0.0}
    t_begin = time.monotonic()
    try:
        deadline = time.monotonic() + args.wait_subscribers
        expect = [t for t in (args.expect or []) if t in pubs]
        if not expect:  # give discovery a moment anyway
            deadline = time.monotonic() + min(0.5, args.wait_subscribers)
        while time.monotonic() < deadline and not stop:
            if expect and all(pubs[t].get_subscription_count() > 0 for t in expect):
                time.sleep(0.2)  # matched: let the reverse direction settle too
                break
            time.sleep(0.05)
        while not stop and time.time() < args.start_at:
            time.sleep(min(0.01, args.start_at - time.time()))
        counts["wait_s"] = time.monotonic() - t_begin
        start = reader.start_ns + int(args.start_offset * 1e9)
        end = start + int(args.duration * 1e9) if args.duration > 0 else None
        while not stop:
            wall0 = time.monotonic()
            offset = time.time_ns() - start if args.restamp else 0
            last_clock = None
            for m in reader.messages(topics, start_ns=start, end_ns=end):
                if stop:
                    break
                if args.rate > 0:
                    delay = wall0 + (m.log_time_ns - start) / 1e9 / args.rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                if clock is not None and m.log_time_ns != last_clock:
                    clock.publish(cdr.encode("rosgraph_msgs/msg/Clock", M.clock_msg(m.log_time_ns + offset)))
                    last_clock = m.log_time_ns
                data = _shift(m.data, offset) if restamp[m.topic] else m.data
                t_pub = time.perf_counter()
                pubs[m.topic].publish(data)
                counts["publish_s"] += time.perf_counter() - t_pub
                counts["messages"] += 1
            counts["loops"] += 1
            if not args.loop:
                break
        counts["play_s"] = time.monotonic() - t_begin - counts["wait_s"]
        time.sleep(0.2)  # let reliable writers hand the last samples over
    finally:
        reader.close()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return counts


def run(args: argparse.Namespace) -> int:
    from vmocap_core.errors import VmocapError

    try:
        counts = play(args)
    except VmocapError as exc:
        print(f"vmocap play: {exc}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(f"vmocap play: published {counts['messages']} messages in {counts['play_s']:.2f} s "
              f"(waited {counts['wait_s']:.2f} s for subscribers, {counts['publish_s']:.2f} s in publish calls)")
    return 0
