"""LPIPS v0.1 (ev3dgs/train/lpips.py) against a second implementation written here in numpy (explicit im2col
convolution, window max pooling, channel normalisation), with random weights saved in the reference package's
exact state-dict layout; its properties; bad weight files through the CLI; `ev3dgs eval --lpips-weights`.

The architecture below is transcribed independently from the reference (torchvision's AlexNet / VGG16
``features`` and lpips' slice boundaries), by position in ``features``, not from ev3dgs's stage table."""
import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ev3dgs import schema
from ev3dgs.cli import main as cli
from ev3dgs.errors import InputError
from ev3dgs.events import Events
from ev3dgs.geometry import intrinsics, look_at
from ev3dgs.splat.model import GaussianModel
from ev3dgs.splat.rasterize import rasterization
from ev3dgs.train.config import TrainConfig
from ev3dgs.train.evaluate import evaluate
from ev3dgs.train.lpips import load_lpips
from ev3dgs.train.trainer import Trainer

# torchvision `features`: ("C", c_in, c_out, kernel, stride, pad), ("R",) relu, ("M", kernel, stride) max pool;
# lpips cuts them into five slices at these positions and taps each slice's output.
FEATURES = {
    "alex": [("C", 3, 64, 11, 4, 2), ("R",), ("M", 3, 2), ("C", 64, 192, 5, 1, 2), ("R",), ("M", 3, 2),
             ("C", 192, 384, 3, 1, 1), ("R",), ("C", 384, 256, 3, 1, 1), ("R",), ("C", 256, 256, 3, 1, 1), ("R",)],
    "vgg": [("C", 3, 64, 3, 1, 1), ("R",), ("C", 64, 64, 3, 1, 1), ("R",), ("M", 2, 2),
            ("C", 64, 128, 3, 1, 1), ("R",), ("C", 128, 128, 3, 1, 1), ("R",), ("M", 2, 2),
            ("C", 128, 256, 3, 1, 1), ("R",), ("C", 256, 256, 3, 1, 1), ("R",), ("C", 256, 256, 3, 1, 1), ("R",),
            ("M", 2, 2), ("C", 256, 512, 3, 1, 1), ("R",), ("C", 512, 512, 3, 1, 1), ("R",),
            ("C", 512, 512, 3, 1, 1), ("R",), ("M", 2, 2), ("C", 512, 512, 3, 1, 1), ("R",),
            ("C", 512, 512, 3, 1, 1), ("R",), ("C", 512, 512, 3, 1, 1), ("R",)],
}
SLICES = {"alex": [0, 2, 5, 8, 10, 12], "vgg": [0, 4, 9, 16, 23, 30]}


def _slice_of(net, i):
    return next(s for s in range(5) if SLICES[net][s] <= i < SLICES[net][s + 1]) + 1


def random_state(net="alex", seed=0) -> dict:
    """A state dict with the reference model's keys and shapes: He-scaled conv weights (so activations neither
    vanish nor explode through the layers), small biases, non-negative lin weights, the v0.1 scaling layer."""
    g = torch.Generator().manual_seed(seed)
    sd = {"scaling_layer.shift": torch.tensor([-.030, -.088, -.188]).view(1, 3, 1, 1),
          "scaling_layer.scale": torch.tensor([.458, .448, .450]).view(1, 3, 1, 1)}
    taps = []
    for i, op in enumerate(FEATURES[net]):
        if op[0] == "C":
            _, cin, cout, k, _, _ = op
            s = _slice_of(net, i)
            sd[f"net.slice{s}.{i}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2 / (cin * k * k)) ** .5
            sd[f"net.slice{s}.{i}.bias"] = 0.1 * torch.randn(cout, generator=g)
            if len(taps) < s:
                taps.append(cout)
            taps[s - 1] = cout
    for k, c in enumerate(taps):
        sd[f"lin{k}.model.1.weight"] = torch.rand(1, c, 1, 1, generator=g)
    return sd


def np_lpips(sd: dict, net: str, a: np.ndarray, b: np.ndarray) -> float:
    """The reference computation in float64 numpy: [0,1] -> [-1,1], scaling layer, trunk, taps, unit-normalise
    over channels (+1e-10), lin-weighted squared difference, mean over pixels, sum over the five taps."""
    w = {k: v.double().numpy() for k, v in sd.items()}

    def taps(img):
        img = img / 255.0 if img.dtype == np.uint8 else img.astype(np.float64)
        x = 2 * img.transpose(2, 0, 1) - 1
        x = (x - w["scaling_layer.shift"][0]) / w["scaling_layer.scale"][0]
        out = []
        for i, op in enumerate(FEATURES[net]):
            if op[0] == "C":
                _, _, _, k, s, p = op
                xp = np.pad(x, ((0, 0), (p, p), (p, p)))
                win = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::s, ::s]
                key = f"net.slice{_slice_of(net, i)}.{i}"
                x = np.tensordot(w[key + ".weight"], win, axes=([1, 2, 3], [0, 3, 4])) + w[key + ".bias"][:, None, None]
            elif op[0] == "R":
                x = np.maximum(x, 0)
            else:
                _, k, s = op
                x = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::s, ::s].max(axis=(3, 4))
            if i + 1 in SLICES[net][1:]:
                out.append(x / (np.sqrt((x ** 2).sum(axis=0, keepdims=True)) + 1e-10))
        return out

    return float(sum((w[f"lin{k}.model.1.weight"][0] * (fa - fb) ** 2).sum(axis=0).mean()
                     for k, (fa, fb) in enumerate(zip(taps(a), taps(b)))))


def tolerance(net: str, u: float) -> float:
    """Relative tolerance of a forward pass in arithmetic with unit round-off u. A dot product of n terms in any
    summation order has a backward error that grows like sqrt(n)*u with high probability (Higham & Mary 2019);
    with random-sign weights its forward condition number sum|w||x| / |sum w x| is ~sqrt(n), so each conv layer
    adds ~n*u of relative error to the feature vector (ReLU, max pooling and normalisation are 1-Lipschitz or
    well conditioned and add a few u); layers add; the squared difference doubles it; x10 covers the tail of
    the distribution. alex: sum n = 9451, so float32 ~1.1e-2 and float64 ~2e-11; a wrong stride, padding,
    pool, tap or constant changes the value by O(1)."""
    n = sum(op[1] * op[3] ** 2 for op in FEATURES[net] if op[0] == "C")
    return 10 * 2 * n * u


U32, U64 = 2.0 ** -24, 2.0 ** -53


@pytest.fixture(scope="module")
def alex_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lpips") / "alex.pth"
    sd = random_state("alex", seed=0)
    torch.save(sd, path)
    return path, sd


@pytest.fixture(scope="module")
def alex64(alex_file):
    return load_lpips(alex_file[0], dtype=torch.float64)


@pytest.fixture(scope="module")
def alex32(alex_file):
    return load_lpips(alex_file[0])


def _images(seed, h, w):
    rng = np.random.default_rng(seed)
    smooth = rng.random((h // 4 + 2, w // 4 + 2, 3)).repeat(4, 0).repeat(4, 1)[:h, :w]  # some structure
    a = (255 * (0.6 * smooth + 0.4 * rng.random((h, w, 3)))).astype(np.uint8)
    b = (255 * rng.random((h, w, 3))).astype(np.uint8)
    return a, b


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_the_numpy_implementation(tmp_path, net):
    sd = random_state(net, seed=1)
    torch.save(sd, tmp_path / "w.pth")
    a, b = _images(2, 64, 48) if net == "alex" else _images(2, 32, 40)
    ref = np_lpips(sd, net, a, b)
    assert ref > 0
    for dtype, u in ((torch.float64, U64), (torch.float32, U32)):
        lp = load_lpips(tmp_path / "w.pth", dtype=dtype)
        assert lp.net == net
        assert lp.distance(a, b) == pytest.approx(ref, rel=tolerance(net, u), abs=0)
    # float [0, 1] input is the same as uint8 / 255
    lp = load_lpips(tmp_path / "w.pth", dtype=torch.float64)
    assert lp.distance(a / 255.0, b / 255.0) == pytest.approx(ref, rel=tolerance(net, U64), abs=0)


@settings(max_examples=15, deadline=None)
@given(h=st.integers(31, 70), w=st.integers(31, 70), seed=st.integers(0, 2 ** 16))
def test_matches_numpy_at_any_size(alex_file, alex64, h, w, seed):
    """Odd sizes exercise the stride-4 conv and the floor of the pools (the last rows/columns a window misses)."""
    a, b = _images(seed, h, w)
    assert alex64.distance(a, b) == pytest.approx(np_lpips(alex_file[1], "alex", a, b),
                                                  rel=tolerance("alex", U64), abs=0)


@settings(max_examples=20, deadline=None)
@given(h=st.integers(31, 64), w=st.integers(31, 64), seed=st.integers(0, 2 ** 16))
def test_properties(alex32, alex64, h, w, seed):
    lp = alex32 if seed % 2 else alex64
    a, b = _images(seed, h, w)
    d = lp.distance(a, b)
    assert lp.distance(a, a) == 0.0 and lp.distance(b, b) == 0.0  # each image runs alone: identical features
    assert lp.distance(b, a) == d  # (x - y)**2 == (y - x)**2 exactly, summed in the same order
    assert d > 0
    # not invariant to what changes an image: brightness, a colour swap, a mirror, an 8x8 patch
    for other in (np.clip(a.astype(int) + 40, 0, 255).astype(np.uint8), a[..., ::-1], a[:, ::-1],
                  np.where(np.pad(np.ones((8, 8, 1), bool), ((10, h - 18), (10, w - 18), (0, 0))), 255 - a, a)):
        assert lp.distance(a, np.ascontiguousarray(other)) > 0


def test_min_size(alex_file, tmp_path):
    """AlexNet's conv1 (11, stride 4, pad 2) gives floor((n - 7) / 4) + 1 pixels; the two 3x3 stride-2 pools
    need >= 3 and >= 3 pixels: n - 7 >= 24 -> n >= 31. VGG16's four 2x2 pools need n >= 16."""
    lp = load_lpips(alex_file[0])
    a, b = _images(0, 31, 31)
    assert lp.distance(a, b) > 0
    for shape in ((30, 64), (64, 30)):
        with pytest.raises(InputError, match="at least 31x31"):
            lp.distance(np.zeros(shape + (3,), np.uint8), np.zeros(shape + (3,), np.uint8))
    torch.save(random_state("vgg"), tmp_path / "vgg.pth")
    vgg = load_lpips(tmp_path / "vgg.pth")
    assert vgg.info["min_size"] == 16
    a, b = _images(0, 16, 16)
    assert vgg.distance(a, b) > 0
    with pytest.raises(InputError, match="at least 16x16"):
        vgg.distance(a[:15], b[:15])


def test_bad_images(alex64):
    a, b = _images(0, 40, 40)
    for x, y in ((a, b[:39]), (a[..., 0], b[..., 0]), (a / 255.0 * 2, b / 255.0), (a.astype(np.int32), b)):
        with pytest.raises(InputError):
            alex64.distance(x, y)


def test_lpips_0_1_4_layout_with_duplicate_lins(tmp_path, alex_file):
    """lpips >= 0.1.4 registers the lin layers twice (lin0.. and lins.0..): same tensors under both names."""
    sd = dict(alex_file[1])
    sd |= {f"lins.{k}.model.1.weight": sd[f"lin{k}.model.1.weight"].clone() for k in range(5)}
    torch.save(sd, tmp_path / "new.pth")
    a, b = _images(3, 40, 40)
    assert load_lpips(tmp_path / "new.pth").distance(a, b) == load_lpips(alex_file[0]).distance(a, b)
    sd["lins.2.model.1.weight"] = sd["lins.2.model.1.weight"] + 1
    torch.save(sd, tmp_path / "differ.pth")
    with pytest.raises(InputError, match="differs"):
        load_lpips(tmp_path / "differ.pth")


# ---- a tiny trained run: `ev3dgs eval --lpips-weights` end to end ----

def _scene(path, width, height):
    rng = np.random.default_rng(0)
    truth = GaussianModel.from_points(rng.uniform(-0.6, 0.6, (200, 3)), rng.integers(30, 255, (200, 3))
                                      .astype(np.uint8), sh_degree=0, init_opacity=0.8)
    K = intrinsics(width, height, 60)
    Kt = torch.as_tensor(K, dtype=torch.float32)

    def draw(c2w):
        vm = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
        with torch.no_grad():
            img, _, _ = rasterization(truth.means, truth.quats_normalised, truth.scales, truth.opacities, truth.sh,
                                      vm, Kt, width, height, sh_degree=0, background=torch.ones(3), backend="cpu")
        return (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)

    poses = [[look_at(3.0 * np.array([np.cos(a + d), np.sin(a + d), 0.5]), [0, 0, 0]) for d in (0, 0.02)]
             for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    frames = [np.stack([draw(p) for p in ps]) for ps in poses]
    exposure = np.array([(v * 200_000, v * 200_000 + 100_000) for v in range(4)])
    test_poses = [look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.4]), [0, 0, 0]) for a in (0.5, 2.5)]
    sc = schema.Scene(
        name="lpips", source="test", camera=schema.Camera(width, height, K=K, background=(1.0, 1.0, 1.0)),
        events=Events(t=exposure[:, 0], x=np.zeros(4), y=np.zeros(4), p=np.ones(4)), sensor=schema.EventSensor(),
        bounds=np.array([[-0.7] * 3, [0.7] * 3]),
        train=schema.Train(images=np.stack([f.mean(0).astype(np.uint8) for f in frames]), exposure=exposure,
                           poses=np.array(poses), pose_t=np.array([[s, e] for s, e in exposure]),
                           sharp=np.stack([f[0] for f in frames]), sharp_poses=np.array([ps[0] for ps in poses])),
        test=schema.Test(images=np.stack([draw(p) for p in test_poses]), poses=np.stack(test_poses)))
    schema.write(sc, path)
    return path


def _run(tmp_path_factory, width, height):
    d = tmp_path_factory.mktemp(f"run{width}")
    cfg = TrainConfig(scene=str(_scene(d / "scene.h5", width, height)), iterations=10, init_points=300,
                      checkpoint_every=10, threads=1, seed=0, sh_degree=0, naive=True, device="cpu")
    Trainer(cfg, d / "run", quiet=True).fit()
    return d / "run"


@pytest.fixture(scope="module")
def run64(tmp_path_factory):
    return _run(tmp_path_factory, 64, 48)


def _panels(png, labels, w, h):
    """The images of a side-by-side eval PNG: each panel padded by one white pixel and, when evaluate captions
    them, under a caption strip in a column as wide as the caption needs (the geometry of evaluate's own
    ``_labelled``, applied to a blank image)."""
    import cv2

    from ev3dgs.train import evaluate as ev

    row = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
    out, x = [], 0
    for label in labels:
        if hasattr(ev, "_labelled"):
            col_w, top = ev._labelled(np.zeros((h, w, 3), np.uint8), label).shape[1], ev.LABEL_HEIGHT
        else:
            col_w, top = w, 0
        x0 = x + 1 + (col_w - w) // 2
        out.append(row[1 + top:1 + top + h, x0:x0 + w])
        x += col_w + 2
    return out


def test_eval_writes_lpips(run64, alex_file, capsys):
    assert cli.main(["eval", str(run64), "--lpips-weights", str(alex_file[0]), "--device", "cpu", "--force"]) == 0
    out = capsys.readouterr().out
    assert "LPIPS v0.1 (alex" in out and out.count("LPIPS 0.") + out.count("LPIPS 1.") >= 3
    m = json.loads((run64 / "metrics.json").read_text())
    assert m["lpips"]["net"] == "alex" and m["lpips"]["version"] == "0.1" and m["lpips_reason"] is None
    for key, n in (("blur_view", 4), ("novel_view", 2), ("blurry_input", 4)):
        assert len(m[key]["lpips_per_view"]) == n and all(v > 0 for v in m[key]["lpips_per_view"])
        assert m[key]["lpips"] == pytest.approx(np.mean(m[key]["lpips_per_view"]), rel=1e-12)
    # each value is LPIPS of the images eval wrote, recomputed by the numpy implementation (float32 network)
    for i in range(2):
        truth, pred = _panels(run64 / "eval" / f"test_{i:03d}.png", ("ground truth", "rendered"), 64, 48)
        ref = np_lpips(alex_file[1], "alex", pred, truth)
        assert m["novel_view"]["lpips_per_view"][i] == pytest.approx(ref, rel=tolerance("alex", U32))
    for i in range(4):
        blurry, pred, sharp = _panels(run64 / "eval" / f"train_{i:03d}.png",
                                      ("blurry input", "rendered", "ground truth"), 64, 48)
        assert m["blur_view"]["lpips_per_view"][i] == pytest.approx(np_lpips(alex_file[1], "alex", pred, sharp),
                                                                     rel=tolerance("alex", U32))
        assert m["blurry_input"]["lpips_per_view"][i] == pytest.approx(
            np_lpips(alex_file[1], "alex", blurry, sharp), rel=tolerance("alex", U32))
    # without weights: null with the reason, and no per-view LPIPS
    assert cli.main(["eval", str(run64), "--device", "cpu", "--force"]) == 0
    m = json.loads((run64 / "metrics.json").read_text())
    assert m["lpips"] is None and "--lpips-weights" in m["lpips_reason"] and "lpips" not in m["blur_view"]


def _bad_files(tmp_path, good_path, sd):
    good = good_path.read_bytes()
    files = {"text": b"not a torch file\n", "empty": b"", "truncated": good[: len(good) // 2]}
    variants = {
        "missing key": {k: v for k, v in sd.items() if k != "lin4.model.1.weight"},
        "extra key": sd | {"net.slice6.12.weight": torch.zeros(1)},
        "wrapped": {"state_dict": sd},
        "wrong shape": sd | {"net.slice1.0.weight": sd["net.slice1.0.weight"].transpose(0, 1).contiguous()},
        "integer": sd | {"net.slice1.0.bias": torch.zeros(64, dtype=torch.int64)},
        "nan": sd | {"net.slice3.6.bias": torch.full((384,), float("nan"))},
        "negative lin": sd | {"lin1.model.1.weight": -sd["lin1.model.1.weight"]},
        "other scaling": sd | {"scaling_layer.scale": torch.ones(1, 3, 1, 1)},
        "a list": [sd],
    }
    for name, obj in variants.items():
        torch.save(obj, tmp_path / "obj.pth")
        files[name] = (tmp_path / "obj.pth").read_bytes()
    torch.save(torch.nn.Linear(2, 2), tmp_path / "module.pth")  # a pickled module: refused by weights_only
    files["pickled module"] = (tmp_path / "module.pth").read_bytes()
    return files


def test_bad_weight_files_exit_2_with_one_line(run64, alex_file, tmp_path, capsys):
    before = (run64 / "metrics.json").read_bytes() if (run64 / "metrics.json").exists() else None
    for name, data in _bad_files(tmp_path, *alex_file).items():
        path = tmp_path / f"{name.replace(' ', '_')}.pth"
        path.write_bytes(data)
        assert cli.main(["eval", str(run64), "--lpips-weights", str(path), "--device", "cpu", "--force"]) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and str(path) in err[0], (name, err)
    for path in (tmp_path / "missing.pth", tmp_path):
        assert cli.main(["eval", str(run64), "--lpips-weights", str(path), "--device", "cpu", "--force"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
    # the evaluation itself went through: PSNR/SSIM written, LPIPS null with what is missing
    assert err[0] == (f"error: LPIPS not computed: {tmp_path}: no such LPIPS weights file (or name a network: "
                      f"alex or vgg); PSNR and SSIM are written to {run64}/metrics.json")
    m = json.loads((run64 / "metrics.json").read_text())
    assert m["lpips"] is None and m["lpips_failed"] and "no such LPIPS weights file" in m["lpips_reason"]
    assert m["test"]["n"] > 0 and np.isfinite(m["test"]["psnr"]) and "lpips" not in m["test"]
    assert (run64 / "metrics.json").read_bytes() != before


def test_eval_refuses_images_too_small_for_the_network(tmp_path_factory, alex_file, capsys):
    run = _run(tmp_path_factory, 40, 30)
    assert cli.main(["eval", str(run), "--lpips-weights", str(alex_file[0]), "--device", "cpu", "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at least 31x31" in err[0] and "40x30" in err[0], err
    assert evaluate(run, write_images=False)["lpips"] is None  # without weights the same run evaluates


def _reference_lpips_module(net="alex"):
    """The `lpips` package (0.1.4, installed by `make setup` with --no-deps: its own torchvision would replace
    our torch) imported with a stand-in for ``torchvision.models`` that builds AlexNet's / VGG16's ``features``
    layer layout from FEATURES above, randomly initialised (pnet_rand=True: no ImageNet weights are fetched).
    Everything else (scaling layer, normalisation, lin layers, spatial average, the shipped v0.1 lin weights)
    is the package's own."""
    import importlib.util
    import sys
    import types

    if importlib.util.find_spec("lpips") is None:
        pytest.skip("the reference lpips package is not installed (make setup installs it)")
    layers = []
    for op in FEATURES[net]:
        if op[0] == "C":
            layers.append(torch.nn.Conv2d(op[1], op[2], op[3], stride=op[4], padding=op[5]))
        elif op[0] == "R":
            layers.append(torch.nn.ReLU(inplace=False))
        else:
            layers.append(torch.nn.MaxPool2d(op[1], op[2]))

    class _Trunk(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.features = torch.nn.Sequential(*layers, torch.nn.MaxPool2d(*((3, 2) if net == "alex" else (2, 2))))

    models = types.ModuleType("torchvision.models")
    models.alexnet = models.vgg16 = lambda *a, **k: _Trunk()
    models.AlexNet_Weights = models.VGG16_Weights = types.SimpleNamespace(IMAGENET1K_V1=None)
    tv = types.ModuleType("torchvision")
    tv.models = models
    saved = {k: sys.modules.get(k) for k in ("torchvision", "torchvision.models")}
    sys.modules.update({"torchvision": tv, "torchvision.models": models})
    try:
        for k in [k for k in sys.modules if k == "lpips" or k.startswith("lpips.")]:
            del sys.modules[k]
        import lpips
        torch.manual_seed(0)
        return lpips.LPIPS(net=net, version="0.1", pretrained=True, pnet_rand=True, verbose=False).eval()
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def test_equals_the_lpips_package_with_its_shipped_lin_weights(tmp_path):
    """A second, independent implementation: the reference package's own forward pass, its shipped v0.1 lin
    weights and a random (He-scaled) AlexNet trunk, saved with its own state_dict() and read by load_lpips.
    Both run in float64 on the same arithmetic (conv, relu, max pool, normalisation, mean), summed in a
    different order: the difference is a few ulps of the ~1e-2 distance, so 1e-12 absolute has margins of 1e3."""
    ref = _reference_lpips_module().double()
    g = torch.Generator().manual_seed(1)
    for m in ref.net.modules():
        if isinstance(m, torch.nn.Conv2d):
            fan = m.weight[0].numel()
            m.weight.data = torch.randn(m.weight.shape, generator=g, dtype=torch.float64) * (2 / fan) ** .5
            m.bias.data = 0.1 * torch.randn(m.bias.shape, generator=g, dtype=torch.float64)
    path = tmp_path / "lpips_alex.pth"
    torch.save({k: v.float() for k, v in ref.state_dict().items()}, path)
    ref = ref.float().double()                     # the same float32-rounded weights on both sides
    ours = load_lpips(path, dtype=torch.float64)
    rng = np.random.default_rng(2)
    for h, w in [(31, 31), (72, 96), (130, 173)]:
        a = rng.random((h, w, 3))
        b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
        t = [torch.from_numpy(x).permute(2, 0, 1)[None] for x in (a, b)]
        with torch.no_grad():
            want = float(ref(*t, normalize=True))
        assert want > 0
        assert abs(ours.distance(a, b) - want) <= 1e-12
