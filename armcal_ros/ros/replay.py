"""
``armcal replay BAG``: publish a bag's messages on their topics with their timing.

Like ``ros2 bag play``: message i is published at wall time t0 + (t_i - t_first) / rate, where
t_i is the bag (receive) time.  Each message is deserialised into its rclpy class with
``rclpy.serialization.deserialize_message`` - an exact copy of the recorded CDR, and a check:
a corrupt message is counted and skipped rather than sent to subscribers that would choke on it.
Publishers are reliable by default (they match reliable and best-effort subscribers);
``--best-effort`` makes them best-effort, as many camera drivers are.

Playback starts once discovery is done, not after a fixed sleep: every subscription the ROS
graph shows on a replayed topic must have matched its publisher (and at least one must exist),
steadily for :data:`MATCH_SETTLE_S`, or ``--delay`` seconds must have passed.  A fixed sleep
either wastes time or, on a loaded machine, loses the bag's first messages to a subscriber that
had not matched yet - and a short recording's first places are a large part of it.
"""

import importlib
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional

from armcal_ros.io.bag import bag_topics, iter_raw
from armcal_ros.params import number_arg


#: How long the matched state must hold before playback starts.  A participant's endpoints are
#: announced together but may be matched one by one; a few discovery round trips (tens of ms on
#: one host) cover that.
MATCH_SETTLE_S = 0.25


@dataclass
class ReplayStats:
    """What a replay did: messages published and skipped per topic, loops, wall time."""

    published: Dict[str, int] = field(default_factory=dict)
    skipped: Dict[str, int] = field(default_factory=dict)
    loops: int = 0
    wall_s: float = 0.0
    bag_s: float = 0.0
    max_lag_s: float = 0.0
    discovery_s: float = 0.0
    matched: Dict[str, int] = field(default_factory=dict)


def message_class(msgtype):
    """``'sensor_msgs/msg/Image'`` -> the rclpy message class (ValueError if not installed)."""
    parts = msgtype.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        raise ValueError(f'msgtype must look like pkg/msg/Type, got {msgtype!r}')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2])
    except (ImportError, AttributeError) as exc:
        raise ValueError(f'message type {msgtype} is not installed: {exc}') from exc


def wait_for_subscribers(node, publishers, timeout, stop, settle=MATCH_SETTLE_S):
    """
    Wait until ``publishers`` ({topic: rclpy publisher}) have matched the graph's subscribers.

    Returns once at least one subscription exists and, for every topic, the publisher has
    matched as many subscriptions as ``node``'s graph shows, and that has held for ``settle``
    seconds; or after ``timeout`` seconds; or when ``stop`` is set.  Returns {topic: matched}.
    A subscription that the graph shows but that never matches (incompatible QoS, e.g. a
    reliable reader of ``--best-effort`` publishers) makes the wait run to ``timeout``.
    """
    t_end = time.monotonic() + timeout
    since = None
    while True:
        matched = {t: p.get_subscription_count() for t, p in publishers.items()}
        ready = (sum(matched.values()) > 0 and
                 all(matched[t] >= node.count_subscribers(t) for t in publishers))
        now = time.monotonic()
        if not ready:
            since = None
        elif since is None:
            since = now
        if (since is not None and now - since >= settle) or now >= t_end:
            return matched
        if stop.wait(min(0.02, max(0.0, t_end - now))):
            return matched


def replay(node, bag, rate=1.0, loop=False, topics=None, reliable=True, depth=100,
           stop: Optional[threading.Event] = None, discovery_timeout=0.0,
           on_publish: Optional[Callable[[str, int, float, object], None]] = None,
           log: Optional[Callable[[str], None]] = None) -> ReplayStats:
    """
    Publish ``bag`` through ``node``'s publishers; return a :class:`ReplayStats`.

    ``rate`` scales time (2.0 plays twice as fast); ``loop`` repeats until ``stop`` is set;
    ``topics`` restricts the topics (default all).  ``on_publish(topic, bag_t_ns, wall_time,
    msg)`` is called after each publish (benchmarks use it to time the node's reaction).
    With ``discovery_timeout`` > 0 playback waits, at most that long, until the publishers
    have matched the subscribers (:func:`wait_for_subscribers`); the wait is in the stats.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate}')
    stop = stop or threading.Event()
    available = bag_topics(bag)
    if topics:
        missing = [t for t in topics if t not in available]
        if missing:
            raise ValueError(f'topics {missing} are not in {bag} (it has {sorted(available)})')
        wanted = list(topics)
    else:
        wanted = sorted(available)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                     reliability=(ReliabilityPolicy.RELIABLE if reliable else
                                  ReliabilityPolicy.BEST_EFFORT),
                     durability=DurabilityPolicy.VOLATILE)
    pubs, classes = {}, {}
    for topic in wanted:
        msgtype = available[topic][0]
        try:
            classes[topic] = message_class(msgtype)
        except ValueError as exc:
            if log:
                log(f'{topic}: {exc}; not replayed')
            continue
        pubs[topic] = node.create_publisher(classes[topic], topic, qos)
    if not pubs:
        raise ValueError(f'{bag}: no topic can be replayed')
    stats = ReplayStats(published={t: 0 for t in pubs}, skipped={t: 0 for t in pubs})
    if discovery_timeout > 0:
        t_wait = time.monotonic()
        stats.matched = wait_for_subscribers(node, pubs, discovery_timeout, stop)
        stats.discovery_s = time.monotonic() - t_wait
        shown = {t: node.count_subscribers(t) for t in stats.matched}
        unmatched = {t: shown[t] - n for t, n in stats.matched.items() if shown[t] > n}
        if log and not stop.is_set() and (unmatched or not sum(stats.matched.values())):
            log(f'after {stats.discovery_s:.1f} s of discovery '
                + (f'subscriptions have not matched on {unmatched} (incompatible QoS?)'
                   if unmatched else 'no subscriber is matched')
                + '; playing anyway')
    t_start = time.monotonic()
    while not stop.is_set():
        t0_wall, t0_bag = None, None
        for raw in iter_raw(bag, list(pubs)):
            if stop.is_set():
                break
            if t0_wall is None:
                t0_wall, t0_bag = time.monotonic(), raw.t_ns
            target = t0_wall + (raw.t_ns - t0_bag) * 1e-9 / rate
            delay = target - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
            stats.max_lag_s = max(stats.max_lag_s, -delay)
            try:
                msg = deserialize_message(raw.rawdata, classes[raw.topic])
            except Exception as exc:  # noqa: B902 - any decoding failure skips that message
                stats.skipped[raw.topic] += 1
                if log:
                    log(f'{raw.topic} at {raw.t_ns} ns: cannot deserialise ({exc}); skipped')
                continue
            pubs[raw.topic].publish(msg)
            stats.published[raw.topic] += 1
            if on_publish is not None:
                on_publish(raw.topic, raw.t_ns, time.time(), msg)
            stats.bag_s = max(stats.bag_s, (raw.t_ns - t0_bag) * 1e-9)
        stats.loops += 1
        if not loop:
            break
    stats.wall_s = time.monotonic() - t_start
    return stats


def add_arguments(p):
    """Arguments of ``armcal replay``."""
    p.add_argument('bag', metavar='BAG', help='rosbag2 bag directory (mcap or sqlite3)')
    p.add_argument('--rate', type=number_arg(float, maximum=1000.0, above=0.0), default=1.0,
                   help='playback rate: 2 plays twice as fast (default 1)')
    p.add_argument('--loop', action='store_true', help='play again and again until Ctrl-C')
    p.add_argument('--topics', nargs='+', metavar='TOPIC', help='only these topics')
    p.add_argument('--best-effort', action='store_true',
                   help='best-effort publishers (default reliable: matches every subscriber)')
    p.add_argument('--delay', type=number_arg(float, 0.0, 3600.0), default=3.0, metavar='S',
                   help='at most this many seconds of discovery: playback starts as soon as '
                        'every subscriber the graph shows on the topics has matched '
                        '(default 3)')
    p.add_argument('--quiet', action='store_true', help='no summary line')


def run(args):
    """Run ``armcal replay``; return the exit status."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    if not args.rate > 0:
        raise ValueError(f'--rate must be > 0, got {args.rate}')
    if not args.delay >= 0:
        raise ValueError(f'--delay must be >= 0 s, got {args.delay}')
    # Ctrl-C and SIGTERM stop the playback in order (publishers before the context).
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('armcal_replay')
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.set())
    result = {}

    def play():
        try:
            result['stats'] = replay(node, args.bag, args.rate, args.loop, args.topics,
                                     reliable=not args.best_effort, stop=stop,
                                     discovery_timeout=args.delay,
                                     log=lambda m: node.get_logger().warning(m))
        except Exception as exc:  # noqa: B902 - reported by the main thread
            result['error'] = exc

    worker = threading.Thread(target=play, name='armcal-replay')
    try:
        worker.start()
        while worker.is_alive():
            worker.join(0.1)
    finally:
        stop.set()
        worker.join(5.0)
        node.destroy_node()
        rclpy.try_shutdown()
    if 'error' in result:
        raise ValueError(str(result['error']))
    stats = result.get('stats')
    if stats is not None and not args.quiet:
        total = sum(stats.published.values())
        skipped = sum(stats.skipped.values())
        print(f'replayed {total} messages ({stats.bag_s:.1f} s of bag in {stats.wall_s:.1f} s, '
              f'{stats.loops} loop(s), max lag {stats.max_lag_s * 1e3:.0f} ms, '
              f'{stats.discovery_s:.1f} s of discovery first)'
              + (f'; skipped {skipped} corrupt' if skipped else ''), file=sys.stderr)
    return 0
