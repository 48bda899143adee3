"""The LPIPS v0.1 weights by network name, the way the reference package `lpips` gets them for
``lpips.LPIPS(net='alex' | 'vgg')``:

* the ImageNet trunk: torchvision's pretrained AlexNet / VGG16 file, fetched once with
  ``torch.hub.load_state_dict_from_url(url, check_hash=True)`` into torch's hub cache
  (``torch.hub.get_dir()/checkpoints/``, i.e. ``$TORCH_HOME/hub/checkpoints/``; the same file torchvision and
  lpips use, so a cache they filled is reused). Only its ``features.I.weight/bias`` are used
  (``classifier.*`` is ignored);
* the v0.1 "lin" layers: ``lpips/weights/v0.1/<net>.pth`` of the installed `lpips` package when it is there
  (and is the published file), else the same file from the lpips GitHub repository, fetched once into the same
  hub cache folder as ``lpips_v0.1_<net>-<sha256 prefix>.pth``.

Every file's full SHA-256 is pinned below and checked on each load (a cached file too, so a damaged cache is
refused rather than silently used); then every key and shape. A file that cannot be downloaded is named with its
URL and the folder to put it in.
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import urllib.error
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import InputError


@dataclass(frozen=True)
class Source:
    url: str
    sha256: str   # of the whole file


# torchvision's ImageNet weights (AlexNet_Weights.IMAGENET1K_V1, VGG16_Weights.IMAGENET1K_V1): the file name
# carries the first 8 hex digits of the SHA-256, which torch.hub's check_hash verifies on download.
TRUNK = {
    "alex": Source("https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
                   "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02"),
    "vgg": Source("https://download.pytorch.org/models/vgg16-397923af.pth",
                  "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0"),
}
# lpips' v0.1 lin layers: the files of lpips 0.1.4, byte-identical to the repository's (unchanged there since 2020).
LIN = {
    "alex": Source("https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/"
                   "alex.pth", "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"),
    "vgg": Source("https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/"
                  "vgg.pth", "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868"),
}


def cache_dir() -> Path:
    """torch's hub cache for weight files (honours $TORCH_HOME and torch.hub.set_dir)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def trunk_file(net: str) -> Path:
    return cache_dir() / os.path.basename(TRUNK[net].url)


def lin_cache_file(net: str) -> Path:
    return cache_dir() / f"lpips_v0.1_{net}-{LIN[net].sha256[:8]}.pth"


def package_lin_file(net: str) -> Path | None:
    """``lpips/weights/v0.1/<net>.pth`` of the installed lpips package (found without importing it), or None."""
    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        return None
    for root in (spec.submodule_search_locations or []) if spec else []:
        f = Path(root) / "weights" / "v0.1" / f"{net}.pth"
        if f.is_file():
            return f
    return None


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def _reason(e: BaseException) -> str:
    if isinstance(e, urllib.error.HTTPError):
        return f"HTTP {e.code} {e.reason}"
    r = getattr(e, "reason", None) or e  # URLError wraps the socket's error
    r = getattr(r, "strerror", None) or r
    return " ".join(str(r).split())[:160] or type(e).__name__


def _place(path: Path, src: Source) -> str:
    """Where to put a file fetched by hand: its folder, and its name when it differs from the URL's."""
    return f"into {path.parent}/" + ("" if path.name == os.path.basename(src.url) else f" as {path.name}")


def _unreachable(net: str, path: Path, src: Source, e: BaseException):
    raise InputError(f"LPIPS {net} needs {path.name}, which could not be downloaded ({_reason(e)}): fetch "
                     f"{src.url} {_place(path, src)} or pass --lpips-weights FILE") from None


def _bad_download(net: str, path: Path, src: Source):
    raise InputError(f"LPIPS {net}: the download of {src.url} does not have the published SHA-256 (starting "
                     f"{src.sha256[:8]}), so it was not kept; retry, or fetch it {_place(path, src)} or pass "
                     "--lpips-weights FILE") from None


def _damaged(net: str, path: Path, src: Source, got: str):
    raise InputError(f"LPIPS {net}: {path} has SHA-256 {got[:16]}..., not the published file's "
                     f"{src.sha256[:16]}... (damaged or replaced): delete it to download it again from {src.url}")


def _verify(net: str, path: Path, src: Source) -> str:
    try:
        got = sha256_of(path)
    except OSError as e:
        raise InputError(f"LPIPS {net}: cannot read {path} ({e.strerror or e})") from None
    if got != src.sha256:
        _damaged(net, path, src, got)
    return got


def _progress() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def _load(net: str, path: Path):
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - the checksum matched, so this is a torch that cannot read the file
        raise InputError(f"LPIPS {net}: cannot read {path} with torch {torch.__version__} "
                         f"({' '.join(str(e).split())[:120] or type(e).__name__})") from None


def fetch_trunk(net: str) -> tuple[dict, Path, str]:
    """(state dict, file, sha256) of torchvision's ImageNet trunk for ``net``, downloaded on first use."""
    src, path = TRUNK[net], trunk_file(net)
    cached = path.is_file()
    if cached:
        _verify(net, path, src)  # torch.hub checks the hash only when it downloads
    try:
        state = torch.hub.load_state_dict_from_url(src.url, check_hash=True, map_location="cpu",
                                                   progress=_progress(), weights_only=True)
    except (urllib.error.URLError, OSError) as e:
        if path.is_file():  # downloaded, then unreadable
            raise InputError(f"LPIPS {net}: cannot read {path} ({_reason(e)})") from None
        _unreachable(net, path, src, e)
    except RuntimeError as e:
        if "invalid hash value" in str(e):  # torch.hub refused the download (and did not keep it)
            _bad_download(net, path, src)
        raise InputError(f"LPIPS {net}: cannot read {path} ({' '.join(str(e).split())[:120]})") from None
    except Exception as e:  # noqa: BLE001 - an unpicklable / truncated file that torch.load rejects
        raise InputError(f"LPIPS {net}: cannot read {path} ({' '.join(str(e).split())[:120] or type(e).__name__}"
                         "); delete it to download it again") from None
    sha = src.sha256 if cached else _verify(net, path, src)
    return state, path, sha


def fetch_lin(net: str) -> tuple[dict, Path, str]:
    """(state dict, file, sha256) of lpips' v0.1 lin layers for ``net``: the installed package's file when it is
    the published one, else the hub cache's copy, downloaded on first use."""
    src = LIN[net]
    pkg = package_lin_file(net)
    try:
        pkg_ok = pkg is not None and sha256_of(pkg) == src.sha256
    except OSError:  # an unreadable install: use the cache instead
        pkg_ok = False
    if pkg_ok:
        return _load(net, pkg), pkg, src.sha256
    path = lin_cache_file(net)
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # verifies the full SHA-256 while downloading; keeps nothing unless it matches
            torch.hub.download_url_to_file(src.url, str(path), hash_prefix=src.sha256, progress=_progress())
        except (urllib.error.URLError, OSError) as e:
            _unreachable(net, path, src, e)
        except RuntimeError as e:
            if "invalid hash value" not in str(e):
                raise
            _bad_download(net, path, src)
    _verify(net, path, src)
    return _load(net, path), path, src.sha256
