from common.memo import BytesMemo


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
