"""Write the fuzz harness's seed corpus (runtime_c/tests/fuzz_corpus/): valid observation sequences of the
static scenario, so libFuzzer starts from frames that pass the CRC, counter and range checks.

Run as ``python -m tests.hil.fuzz_corpus``; the files are deterministic and committed.
"""

from __future__ import annotations

import numpy as np

from embedrl.export.build import RUNTIME_C
from embedrl.hil.codec import Codec
from embedrl.train.scenarios import STATIC

OUT = RUNTIME_C / "tests" / "fuzz_corpus"
FRAME, CLOCK, BUS, LINK = 0, 1, 2, 3


def frame_record(frame_id: int, data: bytes) -> bytes:
    return bytes([FRAME, frame_id - 0x100 + 1, 8]) + data


def clock_record(ms: int) -> bytes:
    return bytes([CLOCK, ms & 0xFF, ms >> 8, *bytes(8)])


def episode(codec: Codec, rng: np.random.Generator, steps: int, first: int) -> bytes:
    out = b""
    for k in range(steps):
        obs = np.array([rng.uniform(f.low, f.high) for f in STATIC.observation], dtype=np.float32)
        frames, _ = codec.encode_observation(obs, first + k)
        out += b"".join(frame_record(f.arbitration_id, bytes(f.data)) for f in frames) + clock_record(30)
    return out


def main() -> None:
    OUT.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    link_down, link_up, bus_off = (
        bytes([kind, a, 0, *bytes(8)]) for kind, a in ((LINK, 1), (LINK, 0), (BUS, 2))
    )
    seeds = {
        "steps": episode(Codec(STATIC), rng, 8, 0),
        # a fresh Codec: counters and steps from 0 again, as after a sender restart
        "timeout-and-recover": episode(Codec(STATIC), rng, 2, 10)
        + clock_record(150)
        + episode(Codec(STATIC), rng, 5, 0),
        "link-and-bus": episode(Codec(STATIC), rng, 2, 0)
        + link_down
        + link_up
        + bus_off
        + episode(Codec(STATIC), rng, 4, 7),
    }
    for name, data in seeds.items():
        (OUT / name).write_bytes(data)


if __name__ == "__main__":
    main()
