#!/usr/bin/env python3
"""Example acquisition publisher for `jointid live`, using the `iceoryx2` package from PyPI.

It publishes excitation and response frames following the jointid iceoryx2 contract
(docs/LIVE.md): one publish-subscribe service per stream named
`<session>/jointid/<stream>`, payload `Slice[c_double]` (type name "f64") with the
`jointid::FrameHeader` user header, the same QoS as jointid (subscriber buffer 8192, safe
overflow off, 4 subscribers, 2 publishers), an event service of the same name that is
notified after every block, and one empty end-of-stream frame per stream at the end.

Input: a JSON-lines file, one sample per line:
    {"sample": 0, "t_ns": 0, "excitation": [..], "response": [..]}
(values in setup channel order, SI units). Usage:

    python publish.py --input frames.jsonl --prefix iox2_ --session default --rate 10000

Note (iceoryx2 issue 1533): a *Python subscriber* sees slice lengths in bytes; readers should
use `header.channels`. Publishing, as here, is not affected.
"""

import argparse
import ctypes
import json
import sys
import time

import iceoryx2 as iox2


class FrameHeader(ctypes.Structure):
    """`jointid::FrameHeader`: #[repr(C)], 24 bytes, alignment 8."""

    _fields_ = [
        ("sample", ctypes.c_uint64),
        ("t_ns", ctypes.c_uint64),
        ("channels", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        return "jointid::FrameHeader"


class Stream:
    """A publisher and a notifier for one jointid stream."""

    def __init__(self, node, session: str, stream: str, max_channels: int):
        name = iox2.ServiceName.new(f"{session}/jointid/{stream}")
        self.service = (
            node.service_builder(name)
            .publish_subscribe(iox2.Slice[ctypes.c_double])
            .user_header(FrameHeader)
            .subscriber_max_buffer_size(8192)
            .history_size(0)
            .enable_safe_overflow(False)
            .max_subscribers(4)
            .max_publishers(2)
            .open_or_create()
        )
        self.publisher = (
            self.service.publisher_builder()
            .initial_max_slice_len(max_channels)
            .allocation_strategy(iox2.AllocationStrategy.Static)
            # Never block acquisition forever: a full subscriber loses this frame
            # (it shows up as a gap in `sample` on the reader's side).
            .backpressure_strategy(iox2.BackpressureStrategy.DiscardData)
            .create()
        )
        event = node.service_builder(name).event().open_or_create()
        self.notifier = event.notifier_builder().create()

    def subscribers(self) -> int:
        return self.service.dynamic_config.number_of_subscribers

    def publish(self, sample: int, t_ns: int, values) -> None:
        uninit = self.publisher.loan_slice_uninit(len(values))
        header = uninit.user_header().contents
        header.sample = sample
        header.t_ns = t_ns
        header.channels = len(values)
        header.flags = 0
        payload = uninit.payload()
        for i, v in enumerate(values):
            payload[i] = float(v)
        uninit.assume_init().send()

    def notify(self) -> None:
        self.notifier.notify()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input", required=True, help="JSON-lines file of samples")
    ap.add_argument("--prefix", default=None, help="iceoryx2 global prefix (as jointid --prefix)")
    ap.add_argument("--session", default="default")
    ap.add_argument("--rate", type=float, default=0.0, help="pace at this rate, Hz (0: as fast as possible)")
    ap.add_argument("--block", type=int, default=64, help="samples per notification")
    ap.add_argument("--wait-subscriber", type=float, default=10.0, help="seconds to wait for jointid live")
    args = ap.parse_args()

    config = iox2.config.default()
    if args.prefix:
        config.global_cfg.prefix = iox2.FileName.new(args.prefix)
    node = (
        iox2.NodeBuilder.new()
        .config(config)
        .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
        .create(iox2.ServiceType.Ipc)
    )
    samples = [json.loads(line) for line in open(args.input) if line.strip()]
    if not samples:
        print("error: no samples in the input", file=sys.stderr)
        return 1
    width = max(len(s["excitation"]) + 0 for s in samples)
    width = max(width, max(len(s["response"]) for s in samples))
    exc = Stream(node, args.session, "excitation", max(64, width))
    resp = Stream(node, args.session, "response", max(64, width))

    deadline = time.monotonic() + args.wait_subscriber
    while exc.subscribers() < 1 or resp.subscribers() < 1:
        if time.monotonic() > deadline:
            print("error: no subscriber (is jointid live running with the same --prefix?)", file=sys.stderr)
            return 1
        time.sleep(0.01)
    time.sleep(0.1)  # let the subscriber threads connect before the first frame

    t0 = time.monotonic()
    for i, s in enumerate(samples):
        exc.publish(s["sample"], s["t_ns"], s["excitation"])
        resp.publish(s["sample"], s["t_ns"], s["response"])
        if (i + 1) % args.block == 0 or i + 1 == len(samples):
            exc.notify()
            resp.notify()
            if args.rate > 0:
                due = t0 + (i + 1) / args.rate
                now = time.monotonic()
                if due > now:
                    time.sleep(due - now)
    # End of stream: one empty frame per stream.
    end = samples[-1]["sample"] + 1
    t_end = samples[-1]["t_ns"]
    exc.publish(end, t_end, [])
    resp.publish(end, t_end, [])
    exc.notify()
    resp.notify()
    print(f"published {len(samples)} samples")
    return 0


if __name__ == "__main__":
    sys.exit(main())
