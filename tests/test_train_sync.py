"""A training step reads nothing back from its device between read-backs (trainer.py, readback.py).

On a CUDA device every read of a device value on the host (``.item()``, ``float(t)``, ``bool(t)``, ``if t:``,
``.tolist()``, ``.cpu()``, ``.numpy()``) and every blocking host-to-device copy (``torch.tensor(data,
device=...)``) makes the host wait for the device. There is no device here, so the test runs the ``cpu``
backend with those entry points patched to record each call and where it came from, and asserts:

* a step that is not a read-back step makes no such call outside the rasterizer backend (the ``cpu`` backend's
  numba kernels read their inputs on the host by design; the ``cuda`` backend, ev3dgs/splat/cuda.py, does not)
  and the host-side draws (the view order and the event pairs come from CPU generators on every device);
* a read-back step makes exactly two: the non-finite guard's flags and the records' values, one ``tolist``
  each, whatever the number of steps read back;
* a densification step (the number of Gaussians changes: its shapes are data-dependent) reads only inside the
  strategy's grow and prune;
* reading back every k steps trains the same model, bit for bit, as reading back at every step, and logs
  the same values;
* a term that calls ``.item()`` again fails the first assertion (the mutation).
"""
from __future__ import annotations

import json
import sys
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_train import cfg, scene_path  # noqa: E402,F401  (the small blob scene and its settings)

from ev3dgs.train.trainer import Trainer  # noqa: E402

READS = ("item", "tolist", "numpy", "cpu", "__bool__", "__float__", "__int__", "__index__", "nonzero")
# the rasterizer backend's modules (the cpu backend reads on the host; not part of the step's glue)
BACKEND = {"cpu.py", "cpu_backward.py", "cpu_tiles.py", "project.py", "project_cpu.py", "rasterize.py",
           "reference.py", "sh.py"}
# host tensors by construction: CPU generators' draws (the view order, the event pairs)
HOST_SITES = {"_next_view", "pair_list"}
SPLAT = Path(__file__).resolve().parent.parent / "ev3dgs" / "splat"
HERE = Path(__file__).resolve()


class Reads:
    """Records (name, function, file) of every patched call made from ev3dgs code outside the backend.
    ``opaque``: file names whose frames stand for device kernels (their own reads are not the caller's)."""

    def __init__(self, opaque: tuple[str, ...] = ()):
        self.calls: list[tuple[str, str, str]] = []
        self.on = True
        self.opaque = opaque

    def record(self, name: str) -> None:
        if not self.on:
            return
        f = sys._getframe(2)
        site = None
        while f is not None:   # up to the first ev3dgs frame: the code that asked for the read
            path = Path(f.f_code.co_filename)
            if path.name in self.opaque or "gsplat" in path.parts:
                return   # inside a stand-in for device kernels
            if "ev3dgs" in path.parts:
                if path.parent == SPLAT and path.name in BACKEND:
                    return   # inside the rasterizer backend
                site = (f.f_code.co_name, path.name)
                break
            if path == HERE:
                return   # the test's own calls
            f = f.f_back
        if site is None or site[0] in HOST_SITES:
            return   # torch's or pytest's own calls; host-side draws
        self.calls.append((name, *site))


@contextmanager
def counting_reads(opaque: tuple[str, ...] = ()):
    reads = Reads(opaque)
    saved = {}

    def wrap(owner, name, when=None):
        real = getattr(owner, name)
        saved[(owner, name)] = real

        def patched(*a, **k):
            if when is None or when(*a, **k):
                reads.record(name)
            return real(*a, **k)
        setattr(owner, name, patched)

    for name in READS:
        wrap(torch.Tensor, name)
    wrap(torch, "equal")
    wrap(torch, "nonzero")
    # blocking host-to-device copies: host data given a device (a CPU tensor on a CUDA run)
    on_device = lambda data, *a, **k: k.get("device") is not None and not torch.is_tensor(data)  # noqa: E731
    wrap(torch, "tensor", on_device)
    wrap(torch, "as_tensor", on_device)
    wrap(torch.Tensor, "new_tensor")
    try:
        yield reads
    finally:
        for (owner, name), real in saved.items():
            setattr(owner, name, real)


def _cfg(scene, **kw):
    # the noise norm with the mean floor (tracked on the device), the frames' noise weighting and the EDI prior
    # on, so every built-in term of a default-like run takes part
    base = dict(iterations=24, checkpoint_every=1000, backend="cpu", device="cpu", event_floor="mean",
                frame_noise=4.0, edi_prior=0.5, readback_every=8)
    base.update(kw)
    return cfg(scene, **base)


def _per_step(trainer: Trainer) -> dict[int, list]:
    """{step: the reads between the end of the previous step and the end of this one}, from a fit."""
    per: dict[int, list] = {}
    with counting_reads() as reads:
        def on_step(tr, rec):
            per[tr.step] = list(reads.calls)
            reads.calls.clear()
        trainer.fit(on_step=on_step)
    return per


def test_no_read_between_read_backs(scene_path, tmp_path):
    tr = Trainer(_cfg(scene_path), tmp_path / "run", quiet=True)
    per = _per_step(tr)
    assert sorted(per) == list(range(1, 25))
    # the last step also writes the checkpoint, which reads the event term's tracked floats
    ckpt = [("__float__", "floor", "events.py"), ("__float__", "blur_mse", "events.py")]
    for step, calls in per.items():
        if step % 8 == 0:   # read-back steps (8, 16, 24: the last is also one)
            assert calls[:2] == [("tolist", "_first_bad", "trainer.py"), ("tolist", "read_back", "readback.py")]
            assert calls[2:] == (ckpt if step == 24 else []), (step, calls)
        else:
            assert calls == [], (step, calls)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 25))
    keys = ("loss", "blur", "event", "edi", "psnr_blurry", "event_weight")
    assert all(isinstance(r[k], float) for r in log for k in keys)


def test_densification_reads_only_in_grow_and_prune(scene_path, tmp_path):
    # a schedule of 60 steps refines at step 21 (refine_start 15, every 10, stop 30: trainer.densify_schedule)
    tr = Trainer(_cfg(scene_path, schedule_length=60, readback_every=100), tmp_path / "run", quiet=True)
    assert (tr.strategy.refine_start, tr.strategy.refine_every, tr.strategy.refine_stop) == (15, 10, 30)
    per = _per_step(tr)
    for step, calls in per.items():
        if step == 21:
            assert calls and {c[2] for c in calls} == {"strategy.py"}, calls
            assert {c[1] for c in calls} <= {"_grow", "_prune", "clone", "split", "prune"}, calls
        elif step == 24:   # the last step reads back (and writes the checkpoint)
            assert Counter(c[0] for c in calls)["tolist"] == 2 and calls[0][1] == "_first_bad", calls
        else:
            assert calls == [], (step, calls)


def _fit(scene, out, **kw):
    tr = Trainer(_cfg(scene, **kw), out, quiet=True)
    tr.fit()
    return tr, [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("opts", [dict(), dict(event_floor="chi2", frame_noise=0.0, edi_prior=0.0),
                                  dict(event_loss=False, edi_prior=0.0)])
def test_reading_back_every_k_steps_trains_the_same_model(scene_path, tmp_path, opts):
    """The read-back interval changes when values reach the host, not what is computed: the same model bytes
    and the same log as reading back at every step (the float path of the floor and the frames' noise weight,
    losses.update_floor and frame_noise.update_mse on floats, is checked against the device path below)."""
    a, log_a = _fit(scene_path, tmp_path / "a", readback_every=1, **opts)
    b, log_b = _fit(scene_path, tmp_path / "b", readback_every=7, **opts)
    for name, p in a.model.params.items():
        assert torch.equal(p, b.model.params[name]), name
    strip = lambda log: [{k: v for k, v in r.items() if k != "seconds"} for r in log]  # noqa: E731
    assert strip(log_a) == strip(log_b)


def test_a_term_that_reads_back_fails_the_check(scene_path, tmp_path, monkeypatch):
    """The mutation: the blur term's source with its log value read at once again (``l_blur.item()``, as it
    was), compiled as the module's own code: a read at every step, which the first test's assertion rejects."""
    import inspect
    import textwrap

    import ev3dgs.train.terms.blur as B

    src = textwrap.dedent(inspect.getsource(B.Blur.loss))
    assert '"blur": l_blur.detach()' in src
    scope = dict(vars(B))
    exec(compile(src.replace('"blur": l_blur.detach()', '"blur": l_blur.item()'), B.__file__, "exec"), scope)
    monkeypatch.setattr(B.Blur, "loss", scope["loss"])
    tr = Trainer(_cfg(scene_path, iterations=3, readback_every=100), tmp_path / "run", quiet=True)
    per = _per_step(tr)
    assert per[1] == per[2] == [("item", "loss", "blur.py")]


# ------------------------------------------------------------------ the device paths against the float paths
_values = st.one_of(st.floats(min_value=1e-12, max_value=1e3), st.sampled_from([0.0, -1.0, math.inf, math.nan]))


def _same(a, b) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@settings(max_examples=200, deadline=None)
@given(floor=st.one_of(st.none(), st.floats(min_value=1e-9, max_value=1e3)), estimate=_values)
def test_device_floor_update_is_the_float_update(floor, estimate):
    """losses.update_floor on 0-dim float64 tensors gives the bits of the float arithmetic (one IEEE operation
    per tensor operation), non-finite estimates included."""
    from ev3dgs.train.losses import update_floor

    f64 = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    want = update_floor(floor, estimate)
    got = update_floor(None if floor is None else f64(floor), f64(estimate))
    assert torch.is_tensor(got) and got.dtype == torch.float64 and _same(float(got), want)


@settings(max_examples=200, deadline=None)
@given(tracked=st.one_of(st.none(), st.floats(min_value=1e-9, max_value=1.0)), mse=_values,
       noise=st.sampled_from([0.0, 1e-5, 4e-4, 0.01]))
def test_device_frame_noise_weight_is_the_float_weight(tracked, mse, noise):
    """frame_noise.update_mse and blur_weight on tensors: the float path's bits (a division written as a tensor
    division, not as Python's scalar-over-tensor, which multiplies by the reciprocal)."""
    from ev3dgs.train.frame_noise import blur_weight, update_mse

    f64 = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    want = update_mse(tracked, mse)
    got = update_mse(None if tracked is None else f64(tracked), f64(mse))
    if want is None:   # a first non-finite step: nothing tracked (None on floats, NaN on the device)
        assert math.isnan(float(got)) and blur_weight(noise, got) == 1.0
        return
    assert _same(float(got), want)
    w = blur_weight(noise, got)
    assert _same(float(w), blur_weight(noise, want))


@pytest.mark.parametrize("stat", ["mean", "median"])
@pytest.mark.parametrize("floor", [None, 3e-3])
def test_device_floor_gives_the_float_floors_loss(stat, floor):
    """noise_event_loss with the floor on the device: the same loss bits and the same estimate as with floats."""
    from ev3dgs.train.losses import noise_event_loss

    g = torch.Generator().manual_seed(5)
    log_l = torch.randn(4, 6, 7, generator=g) * 0.3
    counts = torch.randint(0, 3, (4, 2, 6, 7), generator=g).cumsum(0)   # cumulative ON/OFF counts per pose
    pairs = [(0, 1), (0, 3), (1, 2), (2, 3)]
    tp, tn = torch.tensor(0.25), torch.tensor(0.3)
    ref, est = noise_event_loss(log_l, counts, pairs, tp, tn, floor=floor, floor_stat=stat)
    dev, est_t = noise_event_loss(log_l, counts, pairs, tp, tn, floor_stat=stat, device_floor=True,
                                  floor=None if floor is None else torch.tensor(floor, dtype=torch.float64))
    assert torch.equal(ref, dev) and torch.is_tensor(est_t) and float(est_t) == est


def test_a_record_before_its_read_back_still_prints(scene_path, tmp_path):
    """An on_step callback that formats the record between read-backs (the live viewer's status line) gets
    the values it would get after the read-back (reading them at once), and log.jsonl is unchanged by it."""
    tr = Trainer(_cfg(scene_path, iterations=4, readback_every=100), tmp_path / "run", quiet=True)
    seen = []
    tr.fit(on_step=lambda t, rec: seen.append((f"{rec['loss']:.6f}", f"{rec['psnr_blurry']:.6f}", rec)))
    for loss, psnr, rec in seen:   # the records were turned into floats in place at the end
        assert isinstance(rec["loss"], float) and isinstance(rec["psnr_blurry"], float)
        assert (loss, psnr) == (f"{rec['loss']:.6f}", f"{rec['psnr_blurry']:.6f}")


def test_the_guard_stops_at_the_read_back_after_a_non_finite_step(scene_path, tmp_path, monkeypatch):
    """readback_every 8, checkpoints every 20, the blur loss NaN from step 25 on: the read-back of step 32
    stops the run naming step 25, the checkpoint of step 20 stays (step 40's is never written: a checkpoint
    comes after a read-back that found every step finite), and log.jsonl ends at step 24."""
    from ev3dgs.train.trainer import TrainingError
    import ev3dgs.train.terms.blur as T

    real, calls = T.average_loss, []

    def poisoned(*a, **k):
        calls.append(1)
        out = real(*a, **k)
        return out * float("nan") if len(calls) >= 25 else out

    monkeypatch.setattr(T, "average_loss", poisoned)
    tr = Trainer(_cfg(scene_path, iterations=60, checkpoint_every=20), tmp_path / "run", quiet=True)
    with pytest.raises(TrainingError, match=r"non-finite loss or gradient at step 25 \(blur nan.*ckpt\.pt"):
        tr.fit()
    assert tr.step == 31   # stopped inside step 32, before its update
    ckpt = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)
    assert ckpt["step"] == 20 and all(torch.isfinite(v).all() for v in ckpt["model"].values()
                                      if isinstance(v, torch.Tensor))
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 25))


@pytest.mark.parametrize("opts, sites", [
    (dict(event_floor=None, frame_noise=0.0, edi_prior=0.0), {("chi2_floor", "losses.py"), ("h", "losses.py")}),
    (dict(refine_poses=True, pose_start=0), {("step", "pose_refine.py"), ("<genexpr>", "pose_refine.py")}),
    (dict(threshold_map=True), {("_calibrate", "threshold_map.py")}),
])
def test_the_reads_that_remain_are_where_the_docs_say(scene_path, tmp_path, opts, sites):
    """docs/trainer.md, "Host reads": the chi2 floor's Newton solve (the noise norm's default floor), pose
    refinement's skip of a non-finite gradient and the threshold map's calibration still read inside a step,
    and nothing else does."""
    tr = Trainer(_cfg(scene_path, iterations=6, readback_every=100, **opts), tmp_path / "run", quiet=True)
    per = _per_step(tr)
    for step in range(1, 6):
        assert per[step] and {c[1:] for c in per[step]} <= sites, (step, per[step])


def test_readback_every_is_a_checked_top_level_key():
    from ev3dgs.errors import ConfigError
    from ev3dgs.train.config import TrainConfig

    assert TrainConfig.from_toml({"scene": "s.h5", "readback_every": 50}).readback_every == 50
    assert TrainConfig.from_toml({"scene": "s.h5", "readback_every": "auto"}).readback_every is None
    for bad in (0, -3, "often"):
        with pytest.raises(ConfigError, match="readback_every") as e:
            TrainConfig.from_toml({"scene": "s.h5", "readback_every": bad})
        assert "\n" not in str(e.value)
    # it changes when values reach the host, not the model: a resumed run may change it
    a, b = TrainConfig(scene="s.h5"), TrainConfig(scene="s.h5", readback_every=10)
    assert a.differences(b) == [] and a.to_toml()["readback_every"] == "auto"


@pytest.mark.parametrize("cams", [1, 5])
def test_the_cuda_glue_reads_nothing_back(cams):
    """ev3dgs/splat/cuda.py between gsplat's calls (here gsplat's torch implementations on the CPU, as in
    tests/test_gsplat_parity.py; on a GPU they are kernels): no read of a device value, forward or backward,
    for one camera and for a stack. (gsplat's isect_tiles reads its intersection count itself, once per call.)"""
    pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat with its torch reference functions")
    import test_gsplat_parity as P

    s = P.make_scene(3)
    if cams > 1:
        s.viewmat = torch.stack([s.viewmat] * cams)
    case = P.CASES[0]
    with counting_reads(opaque=("test_gsplat_parity.py",)) as reads:
        img, alpha, meta, leaves = P._render(s, "glue", case, P.TorchOps())
        meta["means2d"].retain_grad()
        (img.sum() + alpha.sum()).backward()
    assert reads.calls == []
    assert meta["means2d"].grad is not None and (img.shape[0] == cams if cams > 1 else img.ndim == 3)
