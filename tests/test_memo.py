import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from common.memo import MEMO_DIR_ENV, BytesMemo, kept_on_disk

ROOT = Path(__file__).resolve().parents[1]


def test_the_least_recently_used_go_first_once_the_bytes_are_over_the_bound():
    memo, made = BytesMemo(max_bytes=10), []

    def make(v):
        return lambda: made.append(v) or v

    assert memo.get("a", make("A"), lambda v: 4) == "A"
    assert memo.get("b", make("B"), lambda v: 4) == "B"
    assert memo.get("a", make("A2"), lambda v: 4) == "A"          # kept: not made again, now the newest
    assert memo.get("c", make("C"), lambda v: 4) == "C"           # 12 bytes: b, the least recent, goes
    assert memo.get("a", make("A3"), lambda v: 4) == "A"
    assert memo.get("b", make("B2"), lambda v: 4) == "B2"         # made again
    assert made == ["A", "B", "C", "B2"]
    assert memo.get("big", make("X"), lambda v: 50) == "X"        # over the bound alone: kept, the rest go
    assert memo.get("a", make("A4"), lambda v: 4) == "A4"


def _arrays(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {"a": rng.normal(size=(40, 3)), "b": rng.integers(0, 9, size=17).astype(np.int16)}


def test_a_result_kept_on_disk_is_read_back_bit_for_bit_by_another_process(tmp_path, monkeypatch):
    monkeypatch.setenv(MEMO_DIR_ENV, str(tmp_path))
    made = []

    def make():
        made.append(1)
        return _arrays(3)

    first = kept_on_disk("things", ("cam1", b"\x01\x02", 0.5), make, dict, dict)
    (written,) = (tmp_path / "things").glob("*.npz")
    assert not list((tmp_path / "things").glob("*.part"))
    # another process with the same key reads the file and makes nothing
    code = ("import sys, numpy as np; from common.memo import kept_on_disk\n"
            "got = kept_on_disk('things', ('cam1', b'\\x01\\x02', 0.5), lambda: sys.exit('made again'), dict, dict)\n"
            "assert not got['a'].flags.writeable\n"
            "np.save(sys.stdout.buffer, got['a']); np.save(sys.stdout.buffer, got['b'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}).stdout
    stream = io.BytesIO(out)
    a, b = np.load(stream), np.load(stream)
    assert a.tobytes() == first["a"].tobytes() and b.dtype == np.int16 and b.tobytes() == first["b"].tobytes()
    # another key, or another name, is made
    kept_on_disk("things", ("cam1", b"\x01\x02", 0.25), make, dict, dict)
    kept_on_disk("others", ("cam1", b"\x01\x02", 0.5), make, dict, dict)
    assert len(made) == 3
    # a file cut short (a process killed while writing cannot leave one, but a full disk can) is made again
    written.write_bytes(written.read_bytes()[:100])
    again = kept_on_disk("things", ("cam1", b"\x01\x02", 0.5), make, dict, dict)
    assert len(made) == 4 and again["a"].tobytes() == first["a"].tobytes()
    assert kept_on_disk("things", ("cam1", b"\x01\x02", 0.5), make, dict, dict)["a"].tobytes() == first["a"].tobytes()
    assert len(made) == 4


def test_without_the_folder_every_call_makes_its_own(monkeypatch):
    monkeypatch.delenv(MEMO_DIR_ENV, raising=False)
    made = []
    for _ in range(2):
        kept_on_disk("things", "key", lambda: made.append(1) or _arrays(1), dict, dict)
    assert len(made) == 2
