"""The job's progress bar: stages in order, monotonic, the total reached; wired through reconstruct."""

import io

import pytest

import capture.progress as P
from capture.progress import Progress, ProgressError


def test_stages_advance_monotonically_to_the_total():
    out = io.StringIO()
    p = Progress({"a": 1.0, "b": 3.0, "c": 1.0}, file=out, total=100, delay=0)
    seen = [p.position]
    p.start("a")
    for _ in range(50):                      # many ticks of unknown count never leave the stage's share (20 %)
        p.tick("loss 1e-3")
        seen.append(p.position)
    assert p.position == pytest.approx(20 * (1 - 0.9 ** 50)) and p.position < 20.0   # 10 % of the rest a tick
    p.start("c")                             # b skipped: its share counts as done
    seen.append(p.position)
    assert p.position == pytest.approx(80.0)
    p.start("b", "late")                     # an earlier stage only changes the note
    p.tick()
    seen.append(p.position)
    assert p.stage == "c" and p.position < 100.0
    p.close()
    seen.append(p.position)
    assert all(b >= a for a, b in zip(seen, seen[1:], strict=False)) and seen[-1] == 100.0
    assert "c" in out.getvalue() and "ETA" in out.getvalue()
    with pytest.raises(ProgressError, match="unknown stage 'd'"):
        p.start("d")
    for bad in ({}, {"a": 0}, {"a": float("inf")}, {"a": True}):
        with pytest.raises(ProgressError):
            Progress(bad, enabled=False)


def test_disabled_prints_nothing_and_still_counts():
    out = io.StringIO()
    p = Progress({"a": 1.0, "b": 1.0}, enabled=False, file=out)
    p.start("a")
    p.tick()
    p.finish("a")
    assert p.position == pytest.approx(50.0)
    p.close()
    assert p.position == 100.0 and out.getvalue() == ""


def test_reconstruct_walks_its_stages_in_order(tmp_path, monkeypatch):
    from capture.reconstruct import reconstruct
    from capture.synth import make_synthetic, small_scene

    runs = []

    class Recorder(Progress):
        def __init__(self, stages, **kw):
            super().__init__(stages, **kw)
            self.log = []
            runs.append(self)

        def _move(self, to):
            super()._move(to)
            self.log.append((self.stage, self.position))

    monkeypatch.setattr(P, "Progress", Recorder)
    make_synthetic(small_scene("ggx-lambert", image_size=32, texture_size=16, n_views=3, supersample=1),
                   tmp_path / "ds")
    reconstruct(tmp_path / "ds", model="ggx-lambert", out_dir=tmp_path / "o", progress=False, footprint=False)
    (p,) = runs
    assert p.names == ["load", "gbuffer", "observe", "solve", "sharing", "joint", "metrics", "outputs"]
    stages = [s for s, _ in p.log]
    order = [s for i, s in enumerate(stages) if s is not None and (i == 0 or s != stages[i - 1])]
    assert order == [s for s in p.names if s in order] and {"gbuffer", "solve", "outputs"} <= set(order)
    positions = [x for _, x in p.log]
    assert all(b >= a for a, b in zip(positions, positions[1:], strict=False))
    assert positions[-1] == p.total == 100.0
    # with footprints (the default) the footprint observations and their solve are stages of their own, entered in
    # order: the footprint solve reports its steps as "footprint", not as the bilinear "joint" refinement
    runs.clear()
    reconstruct(tmp_path / "ds", model="ggx-lambert", out_dir=tmp_path / "o2", progress=False)
    (p,) = runs
    assert p.names == ["load", "gbuffer", "observe", "footprints", "solve", "sharing", "joint", "footprint solve",
                       "metrics", "outputs"]
    stages = [s for s, _ in p.log]
    order = [s for i, s in enumerate(stages) if s is not None and (i == 0 or s != stages[i - 1])]
    assert "footprint solve" in order and order == [s for s in p.names if s in order]
    assert p.log[-1][1] == 100.0
