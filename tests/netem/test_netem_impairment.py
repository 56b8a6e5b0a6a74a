"""The pure impairment model, driven by a fake clock: no sockets, no root, no sleeping."""

from __future__ import annotations

import itertools

import msgspec
import pytest

from rlbridge.netem.impairment import (
    DropReason,
    GilbertElliott,
    Impairment,
    PathModel,
    split_direction,
)

MS = 1e-3


def fates(model: PathModel, count: int, *, step_s: float = 0.01, size: int = 100) -> list[bool]:
    """Admit ``count`` packets ``step_s`` apart; True where the packet was lost."""
    return [
        isinstance(model.admit(i * step_s, size), DropReason)
        for i in range(count)  # fake clock: packet i arrives at i * step_s
    ]


def releases(model: PathModel, times: list[float], size: int = 100) -> list[float]:
    out = []
    for now in times:
        verdict = model.admit(now, size)
        assert not isinstance(verdict, DropReason)
        out.append(verdict)
    return out


def test_clean_path_releases_immediately() -> None:
    model = PathModel(Impairment(), seed=1, name="a_to_b")
    assert releases(model, [0.0, 0.5, 1.0]) == [0.0, 0.5, 1.0]


def test_constant_delay_is_exact_and_never_early() -> None:
    model = PathModel(Impairment(delay_ms=7.5), seed=1, name="a_to_b")
    times = [i * 0.010 for i in range(100)]
    for now, release in zip(times, releases(model, times), strict=True):
        assert release == pytest.approx(now + 7.5 * MS, abs=1e-12)
        assert release >= now + 7.5 * MS - 1e-12


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_seeded_loss_rate_is_within_tolerance(seed: int) -> None:
    model = PathModel(Impairment(loss_pct=10.0), seed=seed, name="a_to_b")
    lost = sum(fates(model, 20_000))
    # Binomial(20000, 0.1): sd = 42 packets; 6 sd either side never flakes.
    assert 2000 - 260 < lost < 2000 + 260


def test_same_seed_same_pattern_other_seed_other_pattern() -> None:
    def pattern(seed: int) -> list[bool]:
        return fates(PathModel(Impairment(loss_pct=5.0), seed=seed, name="a_to_b"), 2000)

    assert pattern(42) == pattern(42)
    assert pattern(42) != pattern(43)


def test_zero_and_full_loss() -> None:
    assert not any(fates(PathModel(Impairment(loss_pct=0.0), seed=1, name="x"), 1000))
    assert all(fates(PathModel(Impairment(loss_pct=100.0), seed=1, name="x"), 1000))


def test_directions_are_independent() -> None:
    imp = Impairment(loss_pct=20.0)
    a_to_b = PathModel(imp, seed=9, name="a_to_b")
    b_to_a = PathModel(imp, seed=9, name="b_to_a")
    # Same seed, different direction: different loss patterns.
    assert fates(a_to_b, 500) != fates(b_to_a, 500)

    # Traffic in the other direction does not shift this direction's pattern.
    alone = fates(PathModel(imp, seed=9, name="a_to_b"), 500)
    busy_ab = PathModel(imp, seed=9, name="a_to_b")
    busy_ba = PathModel(imp, seed=9, name="b_to_a")
    interleaved = []
    for i in range(500):
        for j in range(3):
            busy_ba.admit(i * 0.01 + j * 0.001, 60)
        interleaved.append(isinstance(busy_ab.admit(i * 0.01, 100), DropReason))
    assert interleaved == alone


def test_loss_pattern_does_not_depend_on_delay_or_jitter() -> None:
    plain = fates(PathModel(Impairment(loss_pct=10.0), seed=5, name="a_to_b"), 2000)
    shaped = fates(
        PathModel(Impairment(loss_pct=10.0, delay_ms=15.0, jitter_ms=3.0), seed=5, name="a_to_b"),
        2000,
    )
    assert plain == shaped


def test_jitter_without_reorder_keeps_order_and_bounds() -> None:
    model = PathModel(Impairment(delay_ms=5.0, jitter_ms=4.0), seed=3, name="a_to_b")
    times = [i * 0.001 for i in range(2000)]
    out = releases(model, times)
    assert all(b >= a for a, b in itertools.pairwise(out)), "releases must be non-decreasing"
    for now, release in zip(times, out, strict=True):
        assert release >= now + 1.0 * MS - 1e-12
    # FIFO can hold a packet behind an earlier, later-released one, but never beyond the
    # latest possible release of a packet admitted before it.
    assert max(r - t for t, r in zip(times, out, strict=True)) <= 9.0 * MS + 1e-9
    # and jitter really varies the delay
    assert len({round(r - t, 9) for t, r in zip(times, out, strict=True)}) > 100


def test_jitter_with_reorder_can_reorder() -> None:
    model = PathModel(Impairment(delay_ms=5.0, jitter_ms=4.0, reorder=True), seed=3, name="x")
    out = releases(model, [i * 0.001 for i in range(500)])
    assert any(b < a for a, b in itertools.pairwise(out))


def test_jitter_never_makes_negative_delay() -> None:
    model = PathModel(Impairment(delay_ms=1.0, jitter_ms=5.0, reorder=True), seed=3, name="x")
    times = [i * 0.01 for i in range(1000)]
    assert all(r >= t for t, r in zip(times, releases(model, times), strict=True))


def test_rate_limit_serialises_a_burst() -> None:
    # 1000 bytes at 8000 kbit/s = 1 ms per packet, then 2 ms of propagation delay.
    model = PathModel(Impairment(delay_ms=2.0, rate_kbit=8000.0), seed=1, name="x")
    out = releases(model, [0.0] * 5, size=1000)
    assert out == pytest.approx([(k + 1) * MS + 2 * MS for k in range(5)])
    # An idle link starts serialising at arrival, not at the old busy time.
    assert model.admit(1.0, 1000) == pytest.approx(1.0 + 3 * MS)


def test_queue_limit_tail_drops_and_recovers() -> None:
    model = PathModel(Impairment(delay_ms=10.0, limit=3), seed=1, name="x")
    verdicts = [model.admit(0.0, 100) for _ in range(5)]
    assert verdicts[:3] == pytest.approx([0.010] * 3)
    assert verdicts[3:] == [DropReason.QUEUE_FULL, DropReason.QUEUE_FULL]
    assert model.in_flight(0.005) == 3
    assert model.in_flight(0.011) == 0
    assert not isinstance(model.admit(0.011, 100), DropReason)


def test_reconfigure_shorter_delay_does_not_overtake() -> None:
    model = PathModel(Impairment(delay_ms=20.0), seed=1, name="x")
    first = model.admit(0.0, 100)
    model.reconfigure(Impairment(delay_ms=1.0))
    second = model.admit(0.001, 100)
    assert isinstance(first, float)
    assert isinstance(second, float)
    assert second >= first
    assert model.impairment.delay_ms == 1.0
    # once the old packet is gone, the new delay applies as is
    assert model.admit(0.100, 100) == pytest.approx(0.101)


def test_gilbert_elliott_mean_loss_and_bursts() -> None:
    ge = GilbertElliott(enter_bad_pct=1.0, leave_bad_pct=25.0)
    assert ge.mean_loss_pct == pytest.approx(100.0 / 26.0)
    lost = fates(PathModel(Impairment(bursts=ge), seed=11, name="x"), 50_000)
    rate = 100.0 * sum(lost) / len(lost)
    assert ge.mean_loss_pct * 0.8 < rate < ge.mean_loss_pct * 1.2
    runs = [len(list(group)) for is_lost, group in itertools.groupby(lost) if is_lost]
    mean_burst = sum(runs) / len(runs)
    # mean stay in "bad" is 100 / leave_bad_pct = 4 packets; independent 3.8 % loss
    # would give bursts of ~1.04.
    assert 3.0 < mean_burst < 5.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"delay_ms": -1.0}, "delay_ms"),
        ({"jitter_ms": -0.1}, "jitter_ms"),
        ({"loss_pct": 100.5}, "loss_pct"),
        ({"loss_pct": -1.0}, "loss_pct"),
        ({"rate_kbit": 0.0}, "rate_kbit"),
        ({"limit": 0}, "limit"),
        (
            {"loss_pct": 1.0, "bursts": GilbertElliott(enter_bad_pct=1, leave_bad_pct=10)},
            "not both",
        ),
    ],
)
def test_invalid_impairments_are_rejected(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Impairment(**kwargs)  # type: ignore[arg-type]


def test_gilbert_elliott_validation() -> None:
    with pytest.raises(ValueError, match="forever"):
        GilbertElliott(enter_bad_pct=1.0, leave_bad_pct=0.0)
    with pytest.raises(ValueError, match="enter_bad_pct"):
        GilbertElliott(enter_bad_pct=101.0, leave_bad_pct=1.0)


def test_split_direction() -> None:
    imp = Impairment(delay_ms=3.0)
    clean = Impairment()
    assert split_direction(imp, "both") == (imp, imp)
    assert split_direction(imp, "a_to_b") == (imp, clean)
    assert split_direction(imp, "b_to_a") == (clean, imp)
    with pytest.raises(ValueError, match="direction"):
        split_direction(imp, "sideways")  # type: ignore[arg-type]
    assert clean.is_clean
    assert not imp.is_clean


def test_impairment_survives_the_control_channel_encoding() -> None:
    imp = Impairment(
        delay_ms=7.5,
        jitter_ms=1.0,
        bursts=GilbertElliott(enter_bad_pct=2.0, leave_bad_pct=30.0),
        rate_kbit=1000.0,
        limit=50,
    )
    assert msgspec.json.decode(msgspec.json.encode(imp), type=Impairment) == imp
    with pytest.raises(msgspec.ValidationError, match="loss_pct"):
        msgspec.json.decode(b'{"loss_pct": 200}', type=Impairment)
