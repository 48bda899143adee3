"""LPIPS v0.1 (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric", CVPR 2018)
in plain torch (torchvision does not import with our torch build, so its model code is not used).

The metric, as the reference package `lpips` (github.com/richzhang/PerceptualSimilarity) defines version 0.1:
1. images in [0, 1] are mapped to [-1, 1], then through the scaling layer ``(x - shift) / scale`` with the
   ImageNet-derived constants below (version 0.0 skipped this step: a bug the authors fixed in 0.1);
2. a trunk (AlexNet, or VGG16) computes five feature maps, each tapped after a ReLU;
3. every feature vector (over channels, per pixel) is divided by its Euclidean norm (+ 1e-10);
4. the squared difference of the two images' normalised features is weighted per channel by a learned,
   non-negative 1x1 "lin" layer, averaged over the pixels of that layer, and the five layers are summed.

`load_lpips` takes either

* a network name, ``"alex"`` or ``"vgg"`` (``ev3dgs eval --lpips alex``): the weights come from where
  ``lpips.LPIPS(net=...)`` gets them, torchvision's ImageNet trunk (downloaded once into torch's hub cache,
  ``$TORCH_HOME/hub/checkpoints/``) and lpips' v0.1 lin layers (the installed lpips package's file, else
  downloaded once into the same folder); every file's SHA-256 is pinned and checked (see lpips_fetch.py); or
* one torch file holding the reference model's whole state dict (``--lpips-weights FILE``), e.g. made with

    python -c "import lpips, torch; torch.save(lpips.LPIPS(net='alex', version='0.1').state_dict(), 'lpips_alex.pth')"

  (``net='vgg'`` for the VGG16 trunk). Its keys are ``scaling_layer.shift/scale``, ``net.sliceS.I.weight/bias``
  (S = 1..5, I the index of the conv in torchvision's ``features``), ``linK.model.1.weight`` (K = 0..4) and,
  from lpips 0.1.4 on, the same lin weights again as ``lins.K.model.1.weight``. It is read with
  ``torch.load(weights_only=True)``.

Either way every key, shape and value is checked, and anything else is refused with one line.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError

SHIFT = (-0.030, -0.088, -0.188)  # the scaling layer of v0.1 (per RGB channel, in [-1, 1] units)
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10                  # added to the feature norm, as the reference does

# A trunk: five stages; each is a list of ops, ("pool", kernel, stride) or ("conv", index, c_out, c_in, kernel,
# stride, padding); every conv is followed by a ReLU and each stage's output is one feature tap.
_ALEX = (
    [("conv", 0, 64, 3, 11, 4, 2)],
    [("pool", 3, 2), ("conv", 3, 192, 64, 5, 1, 2)],
    [("pool", 3, 2), ("conv", 6, 384, 192, 3, 1, 1)],
    [("conv", 8, 256, 384, 3, 1, 1)],
    [("conv", 10, 256, 256, 3, 1, 1)],
)


def _vgg_stage(first: int, c_in: int, c_out: int, convs: int, pool: bool) -> list:
    ops, i = ([("pool", 2, 2)], first + 1) if pool else ([], first)
    for _ in range(convs):
        ops.append(("conv", i, c_out, c_in, 3, 1, 1))
        c_in, i = c_out, i + 2
    return ops


_VGG = (_vgg_stage(0, 3, 64, 2, False), _vgg_stage(4, 64, 128, 2, True), _vgg_stage(9, 128, 256, 3, True),
        _vgg_stage(16, 256, 512, 3, True), _vgg_stage(23, 512, 512, 3, True))
TRUNKS = {"alex": _ALEX, "vgg": _VGG}


def expected_shapes(net: str) -> dict[str, tuple]:
    """Every key of the reference model's state dict for trunk ``net`` and its shape (the optional
    ``lins.K`` duplicates of lpips >= 0.1.4 excluded)."""
    shapes = {"scaling_layer.shift": (1, 3, 1, 1), "scaling_layer.scale": (1, 3, 1, 1)}
    for s, stage in enumerate(TRUNKS[net], start=1):
        for op in stage:
            if op[0] == "conv":
                _, i, c_out, c_in, k, _, _ = op
                shapes[f"net.slice{s}.{i}.weight"] = (c_out, c_in, k, k)
                shapes[f"net.slice{s}.{i}.bias"] = (c_out,)
        shapes[f"lin{s - 1}.model.1.weight"] = (1, _channels(stage), 1, 1)
    return shapes


def _channels(stage) -> int:
    return [op for op in stage if op[0] == "conv"][-1][2]


def _out_size(n: int, net: str) -> int:
    """Spatial size of the last feature map for an input of ``n`` pixels (0 when the trunk cannot run)."""
    for stage in TRUNKS[net]:
        for op in stage:
            k, s, p = (op[1], op[2], 0) if op[0] == "pool" else (op[4], op[5], op[6])
            if n + 2 * p < k:
                return 0
            n = (n + 2 * p - k) // s + 1
    return n


def min_size(net: str) -> int:
    """The smallest image side (pixels) the trunk accepts: AlexNet 31, VGG16 16."""
    n = 1
    while _out_size(n, net) < 1:
        n += 1
    return n


FILE_HINT = ("expected one torch file holding lpips.LPIPS(net='alex', version='0.1').state_dict() (how to "
             "make one: \"LPIPS\" in the ev3dgs eval docs, docs/commands/ev3dgs-eval.md)")


def _refuse(path, why: str, hint: str = FILE_HINT):
    raise InputError(f"{path}: {why}; {hint}")


def _short(keys) -> str:
    keys = sorted(keys)
    return ", ".join(keys[:3]) + (f" and {len(keys) - 3} more" if len(keys) > 3 else "")


def _check_state(state, path, hint: str = FILE_HINT) -> tuple[str, dict]:
    """(trunk name, {key: float tensor}) of a state dict that is exactly an LPIPS v0.1 model's; else InputError
    naming ``path``, what is wrong, and ``hint``."""
    def _refuse(where, why):
        raise InputError(f"{where}: {why}; {hint}")

    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        _refuse(path, f"holds a {type(state).__name__}, not a state dict")
    keys = set(state)
    nets = {net: expected_shapes(net) for net in TRUNKS}
    net = max(nets, key=lambda n: len(keys & set(nets[n])))  # the trunk the file is closest to
    shapes = nets[net]
    aliases = {f"lins.{k}.model.1.weight": f"lin{k}.model.1.weight" for k in range(5)}
    missing, extra = set(shapes) - keys, keys - set(shapes) - set(aliases)
    if missing:
        _refuse(path, f"not an LPIPS {net} state dict: missing {_short(missing)}")
    if extra:
        _refuse(path, f"not an LPIPS {net} state dict: unexpected keys {_short(extra)}")
    out = {}
    for k in sorted(keys):
        v = state[k]
        want = shapes.get(k) or shapes[aliases[k]]
        if not torch.is_tensor(v) or not v.is_floating_point():
            _refuse(path, f"{k} is not a floating-point tensor")
        if tuple(v.shape) != want:
            _refuse(path, f"{k} has shape {tuple(v.shape)}, LPIPS {net} needs {want}")
        if not bool(torch.isfinite(v).all()):
            _refuse(path, f"{k} holds NaN or Inf")
        out[k] = v.detach().to("cpu", torch.float64)
    for alias, k in aliases.items():
        if alias in out and not torch.equal(out.pop(alias), out[k]):
            _refuse(path, f"{alias} differs from {k} (the reference stores the same lin layer under both names)")
    for k, ref in (("scaling_layer.shift", SHIFT), ("scaling_layer.scale", SCALE)):
        # float32 storage of the constants: a relative 2**-24 each; 1e-6 absolute covers it with margin
        if not np.allclose(out[k].flatten().numpy(), ref, rtol=0, atol=1e-6):
            _refuse(path, f"{k} = {out[k].flatten().tolist()} is not LPIPS v0.1's {list(ref)}")
    for k in range(5):
        if bool((out[f"lin{k}.model.1.weight"] < 0).any()):
            _refuse(path, f"lin{k}.model.1.weight has negative entries (LPIPS's lin layers are non-negative, so "
                          "that distances are >= 0)")
    return net, out


@dataclass
class Lpips:
    """A loaded LPIPS v0.1 network. ``distance(a, b)`` for two images; ``info`` for metrics.json."""

    net: str
    weights: dict                 # state-dict key -> tensor on ``device`` in ``dtype``
    path: str
    sha256: str
    device: torch.device
    dtype: torch.dtype

    @property
    def info(self) -> dict:
        return {"net": self.net, "version": "0.1", "weights": self.path, "sha256": self.sha256,
                "min_size": min_size(self.net)}

    def check_size(self, width: int, height: int) -> None:
        m = min_size(self.net)
        if width < m or height < m:
            raise InputError(f"LPIPS ({self.net}) needs images of at least {m}x{m} pixels, these are "
                             f"{width}x{height}; evaluate without LPIPS (no --lpips / --lpips-weights)")

    def _as_batch(self, img) -> torch.Tensor:
        """(H, W, 3) uint8, or float in [0, 1] (numpy or torch) -> (1, 3, H, W) in [-1, 1]."""
        t = torch.as_tensor(np.asarray(img) if not torch.is_tensor(img) else img)
        if t.ndim != 3 or t.shape[2] != 3:
            raise InputError(f"LPIPS needs (H, W, 3) RGB images, got shape {tuple(t.shape)}")
        if t.dtype == torch.uint8:
            t = t.to(self.dtype) / 255.0
        elif t.is_floating_point():
            if not bool(torch.isfinite(t).all()) or float(t.min()) < 0 or float(t.max()) > 1:
                raise InputError("LPIPS needs float images in [0, 1] (finite)")
            t = t.to(self.dtype)
        else:
            raise InputError(f"LPIPS needs uint8 or float images, got {t.dtype}")
        self.check_size(t.shape[1], t.shape[0])
        return (2 * t - 1).permute(2, 0, 1)[None].to(self.device)

    @torch.no_grad()
    def features(self, img) -> list[torch.Tensor]:
        """The five channel-normalised feature maps of one image, each (1, C, h, w)."""
        w = self.weights
        x = (self._as_batch(img) - w["scaling_layer.shift"]) / w["scaling_layer.scale"]
        taps = []
        for s, stage in enumerate(TRUNKS[self.net], start=1):
            for op in stage:
                if op[0] == "pool":
                    x = F.max_pool2d(x, op[1], op[2])
                else:
                    _, i, _, _, _, stride, pad = op
                    x = F.relu(F.conv2d(x, w[f"net.slice{s}.{i}.weight"], w[f"net.slice{s}.{i}.bias"],
                                        stride=stride, padding=pad))
            taps.append(x / (torch.sqrt((x * x).sum(dim=1, keepdim=True)) + NORM_EPS))
        return taps

    @torch.no_grad()
    def distance(self, a, b) -> float:
        """LPIPS between two (H, W, 3) images of equal shape (uint8, or float in [0, 1])."""
        if tuple(np.shape(a)) != tuple(np.shape(b)):
            raise InputError(f"LPIPS needs two images of the same shape, got {np.shape(a)} and {np.shape(b)}")
        # each image through the trunk on its own: d(x, x) is exactly 0 and d(a, b) exactly d(b, a)
        fa, fb = self.features(a), self.features(b)
        total = 0.0
        for k, (x, y) in enumerate(zip(fa, fb)):
            lin = self.weights[f"lin{k}.model.1.weight"]
            total += float((((x - y) ** 2) * lin).sum(dim=1).mean())
        return total


NETWORKS = tuple(TRUNKS)  # the names load_lpips fetches weights for: "alex", "vgg"


def _part(net: str, path: Path, state, mapping: dict[str, str], ignore: tuple[str, ...] = ()) -> dict:
    """The tensors of one fetched file under our key names: ``mapping`` {file key: our key}, exactly those keys
    (besides ones starting with ``ignore``), each a floating-point tensor of the shape LPIPS needs."""
    hint = "delete it to download it again, or pass --lpips-weights FILE"
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        _refuse(path, f"holds a {type(state).__name__}, not a state dict", hint)
    missing = set(mapping) - set(state)
    extra = {k for k in state if k not in mapping and not k.startswith(ignore)}
    if missing:
        _refuse(path, f"not the LPIPS {net} weights: missing {_short(missing)}", hint)
    if extra:
        _refuse(path, f"not the LPIPS {net} weights: unexpected keys {_short(extra)}", hint)
    shapes, out = expected_shapes(net), {}
    for k, ours in mapping.items():
        v = state[k]
        if not torch.is_tensor(v) or not v.is_floating_point():
            _refuse(path, f"{k} is not a floating-point tensor", hint)
        if tuple(v.shape) != shapes[ours]:
            _refuse(path, f"{k} has shape {tuple(v.shape)}, LPIPS {net} needs {shapes[ours]}", hint)
        out[ours] = v
    return out


def _fetched(net: str) -> tuple[dict, str, str]:
    """(LPIPS state dict, "trunk file + lin file", "trunk sha256 + lin sha256") assembled from torchvision's
    ImageNet trunk and lpips' v0.1 lin layers, fetched into torch's hub cache on first use (lpips_fetch.py)."""
    from . import lpips_fetch

    trunk, trunk_path, trunk_sha = lpips_fetch.fetch_trunk(net)
    lin, lin_path, lin_sha = lpips_fetch.fetch_lin(net)
    convs = {}
    for s, stage in enumerate(TRUNKS[net], start=1):
        for op in stage:
            if op[0] == "conv":
                convs |= {f"features.{op[1]}.{w}": f"net.slice{s}.{op[1]}.{w}" for w in ("weight", "bias")}
    state = {"scaling_layer.shift": torch.tensor(SHIFT, dtype=torch.float32).view(1, 3, 1, 1),
             "scaling_layer.scale": torch.tensor(SCALE, dtype=torch.float32).view(1, 3, 1, 1)}
    state |= _part(net, trunk_path, trunk, convs, ignore=("classifier.",))  # torchvision's classifier: unused
    state |= _part(net, lin_path, lin, {f"lin{k}.model.1.weight": f"lin{k}.model.1.weight" for k in range(5)})
    return state, f"{trunk_path} + {lin_path}", f"{trunk_sha} + {lin_sha}"


def load_lpips(path: str | Path, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> Lpips:
    """LPIPS v0.1 from a network name, "alex" or "vgg" (its weights fetched the way the lpips package does, on
    first use), or from one weights file (see the module docstring); InputError names what is wrong.

    For a network name, ``info["weights"]`` is "<trunk file> + <lin file>" and ``info["sha256"]`` their two
    SHA-256s joined the same way; for a file, that file and its SHA-256."""
    if isinstance(path, str) and path in NETWORKS:
        state, where, sha = _fetched(path)
        net, weights = _check_state(state, where, "delete these files to download them again, or pass "
                                                  "--lpips-weights FILE")
        dev = torch.device(device)
        return Lpips(net=net, weights={k: v.to(dev, dtype) for k, v in weights.items()}, path=where, sha256=sha,
                     device=dev, dtype=dtype)
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such LPIPS weights file (or name a network: {' or '.join(NETWORKS)})")
    try:
        data = p.read_bytes()
    except OSError as e:
        raise InputError(f"{p}: cannot read the LPIPS weights ({e.strerror or e})") from None
    if not data.startswith((b"PK\x03\x04", b"\x80")):  # torch.save writes a zip archive (a pickle before 1.6)
        _refuse(p, "not a torch file (neither a zip archive nor a pickle)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure to unpickle means "not a usable torch weights file"
        text = " ".join(str(e).split())
        if "weights only load failed" in text.lower() or "unsupported global" in text.lower():
            _refuse(p, "holds Python objects besides tensors (a pickled model? save model.state_dict())")
        _refuse(p, f"a damaged or truncated torch file ({text.split('. ')[0][:120] or type(e).__name__})")
    net, weights = _check_state(state, p)
    dev = torch.device(device)
    return Lpips(net=net, weights={k: v.to(dev, dtype) for k, v in weights.items()}, path=str(p),
                 sha256=hashlib.sha256(data).hexdigest(), device=dev, dtype=dtype)
