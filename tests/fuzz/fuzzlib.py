"""A small seeded fuzzer: mutate valid inputs, load them, and demand a clean load or the project's error.

A format is one function returning a `Target`: the valid files (relative path -> bytes), the file (or
".") handed to the loader, the loader, the error types it may raise, and optionally a check of what it
loaded and codecs (e.g. gunzip / gzip) so that the decoded content is mutated too, not only its
wrapper. `run_case(target, name, i, workdir)` applies case i's mutations (seeded by `name:i`, so every
case is reproducible) and loads the result under a bound of CPU time (not wall time: a loaded CI machine
must not fail a case) and of memory.
"""

from __future__ import annotations

import random
import re
import signal
import struct
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

TIME_LIMIT_S = 2.0  # CPU seconds of this process per case (a valid small input loads in milliseconds)
HANG_LIMIT_S = 10.0  # CPU seconds after which SIGPROF stops a case that spins (reported as a hang)
WALL_LIMIT_S = 120.0  # SIGALRM stops a case blocked without using CPU (e.g. waiting forever)
MEMORY_LIMIT = 64 * 2**20  # peak bytes traced by tracemalloc (Python + numpy allocations) per case

HUGE_NUMBERS = [b"99999999999999999999", b"4294967295", b"2147483648", b"-1", b"1e308", b"1e30", b"-1e30",
                b"nan", b"inf", b"-inf", b"0", b"-0", b"1e-320"]
BINARY_WORDS = [struct.pack("<f", float("nan")), struct.pack("<f", float("inf")), struct.pack("<f", 1e30),
                struct.pack("<I", 0xFFFFFFFF), struct.pack("<I", 0x7FFFFFFF), struct.pack(">I", 0xFFFFFFFF),
                b"\0\0\0\0"]
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?")


@dataclass
class Target:
    files: dict[str, bytes]
    entry: str  # path (relative to the case folder) given to `load`; "." for the folder itself
    load: Callable[[Path], object]
    errors: tuple[type[BaseException], ...]
    check: Callable[[object], None] = lambda obj: None
    mutable: tuple[str, ...] = ()  # files that are mutated (default: the entry file)
    codecs: dict[str, tuple[Callable[[bytes], bytes], Callable[[bytes], bytes]]] = field(default_factory=dict)


# ---- mutations ---------------------------------------------------------------------------------------
def _bit_flips(data: bytearray, rng: random.Random) -> str:
    n = rng.randint(1, 8)
    for _ in range(n):
        i = rng.randrange(len(data))
        data[i] ^= 1 << rng.randrange(8)
    return f"{n} bit flips"


def _byte_set(data: bytearray, rng: random.Random) -> str:
    i = rng.randrange(len(data))
    data[i] = rng.choice((0x00, 0xFF, 0x7F, 0x80, 0x0A, 0x22, 0x3C))
    return f"byte {i} set"


def _truncate(data: bytearray, rng: random.Random) -> str:
    i = rng.randrange(len(data))
    del data[i:]
    return f"truncated at {i}"


def _huge_number(data: bytearray, rng: random.Random) -> str:
    spans = [m.span() for m in _NUMBER.finditer(bytes(data))]
    if not spans:
        return _binary_word(data, rng)
    a, b = rng.choice(spans)
    value = rng.choice(HUGE_NUMBERS)
    data[a:b] = value
    return f"number at {a} -> {value.decode()}"


def _binary_word(data: bytearray, rng: random.Random) -> str:
    if len(data) < 4:
        return _truncate(data, rng)
    i = rng.randrange(0, len(data) - 3) & ~3 if rng.random() < 0.7 else rng.randrange(0, len(data) - 3)
    data[i:i + 4] = rng.choice(BINARY_WORDS)
    return f"word at {i}"


def _duplicate(data: bytearray, rng: random.Random) -> str:
    a = rng.randrange(len(data))
    b = min(len(data), a + rng.randint(1, 256))
    data[b:b] = data[a:b] * rng.randint(1, 50)
    return f"duplicated [{a}:{b}]"


def _delete(data: bytearray, rng: random.Random) -> str:
    a = rng.randrange(len(data))
    del data[a:a + rng.randint(1, 64)]
    return f"deleted at {a}"


MUTATIONS = [_bit_flips, _byte_set, _truncate, _huge_number, _huge_number, _binary_word, _duplicate, _delete]


def mutate(data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    """1-3 random mutations of `data` -> (mutated bytes, what was done)."""
    buf, done = bytearray(data), []
    for _ in range(rng.randint(1, 3)):
        if not buf:
            break
        done.append(rng.choice(MUTATIONS)(buf, rng))
    return bytes(buf), done


# ---- running a case ----------------------------------------------------------------------------------
class CaseHung(Exception):
    pass


def _alarm(signum, frame):
    what = f"{HANG_LIMIT_S} CPU s" if signum == signal.SIGPROF else f"{WALL_LIMIT_S} s"
    raise CaseHung(f"still running after {what}")


def run_case(target: Target, name: str, i: int, workdir: Path) -> str:
    """Mutate, write, load. Returns "loaded" or "refused"; AssertionError on an escape, hang or blow-up."""
    rng = random.Random(f"{name}:{i}")
    rel = rng.choice(target.mutable or (target.entry,))
    data, codec = target.files[rel], target.codecs.get(rel)
    if codec is not None and rng.random() < 0.7:  # mutate the decoded content, then re-encode it
        inner, done = mutate(codec[0](data), rng)
        data, done = codec[1](inner), ["decoded: " + d for d in done]
    else:
        data, done = mutate(data, rng)
    case_dir = workdir / f"{name}-{i}"
    for path, content in target.files.items():
        (case_dir / path).parent.mkdir(parents=True, exist_ok=True)
        (case_dir / path).write_bytes(data if path == rel else content)
    what = f"fuzz case {name}:{i} ({rel}: {'; '.join(done)}; input kept in {case_dir})"
    old = signal.signal(signal.SIGALRM, _alarm), signal.signal(signal.SIGPROF, _alarm)
    signal.setitimer(signal.ITIMER_REAL, WALL_LIMIT_S)
    signal.setitimer(signal.ITIMER_PROF, HANG_LIMIT_S)
    tracemalloc.start()
    t0 = time.process_time()
    outcome, obj = "refused", None
    try:
        obj = target.load(case_dir / target.entry)
        outcome = "loaded"
    except target.errors:
        pass
    except CaseHung as err:
        raise AssertionError(f"{what}: hung ({err})") from None
    except Exception as err:  # noqa: BLE001 - the point of the fuzzer
        raise AssertionError(f"{what}: escaped as {type(err).__name__}: {err}") from err
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGALRM, old[0])
        signal.signal(signal.SIGPROF, old[1])
        elapsed = time.process_time() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert elapsed < TIME_LIMIT_S, f"{what}: took {elapsed:.2f} CPU s"
    assert peak < MEMORY_LIMIT, f"{what}: peak memory {peak / 2**20:.0f} MiB"
    if outcome == "loaded":
        try:
            target.check(obj)
        except Exception as err:  # noqa: BLE001 - an assertion, or a loaded result that fails when used
            raise AssertionError(f"{what}: loaded an invalid result: {type(err).__name__}: {err}") from None
    return outcome
