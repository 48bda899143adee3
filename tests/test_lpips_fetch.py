"""`load_lpips("alex" | "vgg")`: the trunk and lin files fetched into torch's hub cache the way the reference
`lpips` package gets them, offline: TORCH_HOME points into tmp_path and the "servers" are file:// URLs to
files made here (a random trunk in torchvision's key layout, named with its own SHA-256 prefix, so torch.hub's
check_hash and our full SHA-256 check run for real), with the pinned URLs / hashes swapped for theirs."""
import hashlib
import socket
import urllib.error

import numpy as np
import pytest
import torch
from test_lpips import _images, _reference_lpips_module, random_state, tolerance

from ev3dgs.errors import InputError
from ev3dgs.train import lpips_fetch
from ev3dgs.train.lpips import load_lpips
from ev3dgs.train.metrics import lpips_unavailable_reason

U32, U64 = 2.0 ** -24, 2.0 ** -53
TRUNK_NAMES = {"alex": "alexnet-owt", "vgg": "vgg16"}


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _one_line(e) -> str:
    msg = str(e.value)
    assert "\n" not in msg and msg.strip() == msg
    assert " here" not in msg and "sandbox" not in msg.lower() and "this machine" not in msg
    return msg


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """TORCH_HOME in tmp_path; every download counted (and passed on to torch.hub's own downloader)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None)  # no torch.hub.set_dir from elsewhere
    calls = []
    real = torch.hub.download_url_to_file

    def counting(url, dst, *a, **k):
        calls.append(url)
        return real(url, dst, *a, **k)

    monkeypatch.setattr(torch.hub, "download_url_to_file", counting)
    assert lpips_fetch.cache_dir() == tmp_path / "torch" / "hub" / "checkpoints"
    return calls


def _reference(net, seed):
    """The reference package's model with a random He-scaled trunk and random non-negative lin weights."""
    ref = _reference_lpips_module(net)
    g = torch.Generator().manual_seed(seed)
    for m in ref.net.modules():
        if isinstance(m, torch.nn.Conv2d):
            m.weight.data = torch.randn(m.weight.shape, generator=g) * (2 / m.weight[0].numel()) ** .5
            m.bias.data = 0.1 * torch.randn(m.bias.shape, generator=g)
    for k in range(5):
        lin = getattr(ref, f"lin{k}").model[1]
        lin.weight.data = torch.rand(lin.weight.shape, generator=g)
    return ref


def _serve(tmp_path, monkeypatch, net, ref, lin=True, legacy=False):
    """Write the reference model's trunk in torchvision's layout (features.I.*, plus a classifier the loader
    ignores) as <name>-<its sha256 prefix>.pth (``legacy``: in torch's pre-1.6 pickle format, as torchvision's
    published files are), and its lin layers in lpips' layout; point the pins at them."""
    server = tmp_path / "server"
    server.mkdir(exist_ok=True)
    sd = ref.state_dict()
    trunk = {"features." + k.split(".", 2)[2]: v.clone() for k, v in sd.items() if k.startswith("net.slice")}
    trunk |= {"classifier.1.weight": torch.zeros(4, 8), "classifier.1.bias": torch.zeros(4)}
    tmp = server / "trunk.tmp"
    torch.save(trunk, tmp, _use_new_zipfile_serialization=not legacy)
    sha = _sha(tmp)
    trunk_file = tmp.rename(server / f"{TRUNK_NAMES[net]}-{sha[:8]}.pth")
    monkeypatch.setitem(lpips_fetch.TRUNK, net, lpips_fetch.Source(trunk_file.as_uri(), sha))
    files = {"trunk": trunk_file}
    if lin:
        lin_file = server / f"{net}.pth"
        torch.save({f"lin{k}.model.1.weight": sd[f"lin{k}.model.1.weight"].clone() for k in range(5)}, lin_file)
        monkeypatch.setitem(lpips_fetch.LIN, net, lpips_fetch.Source(lin_file.as_uri(), _sha(lin_file)))
        files["lin"] = lin_file
    return files


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_fetched_model_equals_the_lpips_package(hub, tmp_path, monkeypatch, net):
    """Downloaded, checked, assembled, then the same distances as the reference package's own forward pass with
    the same trunk and lin weights. Each side is within tolerance(net, u) (test_lpips.py: float accumulation
    over the conv fan-ins) of the exact value, so they differ by at most twice that."""
    ref = _reference(net, seed=3)
    files = _serve(tmp_path, monkeypatch, net, ref)
    lp = load_lpips(net)
    assert hub == [files["trunk"].as_uri(), files["lin"].as_uri()]
    cache = lpips_fetch.cache_dir()
    trunk_cached, lin_cached = cache / files["trunk"].name, lpips_fetch.lin_cache_file(net)
    assert trunk_cached.read_bytes() == files["trunk"].read_bytes()
    assert lin_cached.read_bytes() == files["lin"].read_bytes() and lin_cached.parent == cache
    assert lp.net == net and lp.info["weights"] == f"{trunk_cached} + {lin_cached}"
    assert lp.info["sha256"] == f"{_sha(files['trunk'])} + {_sha(files['lin'])}"
    for k, v in ref.state_dict().items():  # every tensor landed under the right name, unchanged
        if not k.startswith("lins."):
            assert torch.equal(lp.weights[k], v.float()), k
    lp64 = load_lpips(net, dtype=torch.float64)
    rng = np.random.default_rng(4)
    sizes = [(31, 31), (72, 96)] if net == "alex" else [(16, 16), (40, 56)]
    for h, w in sizes:
        a = rng.random((h, w, 3))
        b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
        t = [torch.from_numpy(x).permute(2, 0, 1)[None] for x in (a, b)]
        with torch.no_grad():
            want32 = float(ref.float()(*[x.float() for x in t], normalize=True))
            want64 = float(ref.double()(*t, normalize=True))
        assert want64 > 0
        assert lp.distance(a, b) == pytest.approx(want32, rel=2 * tolerance(net, U32), abs=0)
        assert lp64.distance(a, b) == pytest.approx(want64, rel=2 * tolerance(net, U64), abs=0)


def test_second_load_reuses_the_cache(hub, tmp_path, monkeypatch):
    ref = _reference("alex", seed=5)
    files = _serve(tmp_path, monkeypatch, "alex", ref, legacy=True)
    assert not files["trunk"].read_bytes().startswith(b"PK")
    a, b = _images(1, 40, 48)
    d = load_lpips("alex").distance(a, b)
    assert len(hub) == 2
    for f in files.values():
        f.unlink()  # the "server" is gone: only the cache can serve now
    again = load_lpips("alex")
    assert len(hub) == 2 and again.distance(a, b) == d


def test_lin_layers_from_the_installed_lpips_package(hub, tmp_path, monkeypatch):
    """With the real pinned lin file: the installed lpips package's weights/v0.1/alex.pth is it (SHA-256 pinned
    from lpips 0.1.4), so only the trunk is downloaded."""
    pkg = lpips_fetch.package_lin_file("alex")
    if pkg is None:
        pytest.skip("the reference lpips package is not installed (make setup installs it)")
    assert _sha(pkg) == lpips_fetch.LIN["alex"].sha256
    assert _sha(lpips_fetch.package_lin_file("vgg")) == lpips_fetch.LIN["vgg"].sha256
    files = _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=6), lin=False)
    lp = load_lpips("alex")
    assert hub == [files["trunk"].as_uri()] and lp.info["weights"].endswith(f" + {pkg}")
    shipped = torch.load(pkg, map_location="cpu", weights_only=True)
    for k, v in shipped.items():
        assert torch.equal(lp.weights[k], v)
    assert not lpips_fetch.lin_cache_file("alex").exists()


def _flip_a_byte(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("which", ["trunk", "lin"])
def test_a_damaged_cached_file_is_refused(hub, tmp_path, monkeypatch, which):
    _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=7))
    load_lpips("alex")
    cached = lpips_fetch.trunk_file("alex") if which == "trunk" else lpips_fetch.lin_cache_file("alex")
    _flip_a_byte(cached)
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    msg = _one_line(e)
    assert str(cached) in msg and "SHA-256" in msg and "delete it" in msg
    assert len(hub) == 2  # refused before anything else was tried
    cached.unlink()  # as the message says: then it downloads again
    load_lpips("alex")
    assert len(hub) == 3


def test_a_download_with_the_wrong_hash_is_refused_and_not_kept(hub, tmp_path, monkeypatch):
    files = _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=8))
    # the trunk's contents change after its name was given: torch.hub's check_hash (name prefix) refuses it
    _flip_a_byte(files["trunk"])
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    msg = _one_line(e)
    assert files["trunk"].as_uri() in msg and "SHA-256" in msg and "not kept" in msg
    assert not lpips_fetch.trunk_file("alex").exists() and len(hub) == 1
    # the name prefix matches but the rest of the pinned SHA-256 does not: our full check refuses it
    files = _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=8))
    src = lpips_fetch.TRUNK["alex"]
    monkeypatch.setitem(lpips_fetch.TRUNK, "alex", lpips_fetch.Source(src.url, src.sha256[:8] + "0" * 56))
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    assert str(lpips_fetch.trunk_file("alex")) in _one_line(e) and "SHA-256" in str(e.value)
    # the lin file: downloaded with the full pinned SHA-256 as torch.hub's hash_prefix
    lpips_fetch.trunk_file("alex").unlink()
    files = _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=8))
    _flip_a_byte(files["lin"])
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    assert files["lin"].as_uri() in _one_line(e) and "not kept" in str(e.value)
    assert not lpips_fetch.lin_cache_file("alex").exists()
    assert [p.name for p in lpips_fetch.cache_dir().iterdir()] == [files["trunk"].name]  # no partial files


def _offline(monkeypatch):
    def no_network(url, dst, *a, **k):
        raise urllib.error.URLError(socket.gaierror(-3, "Temporary failure in name resolution"))

    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)


def test_without_network_one_line_names_the_file_and_folder(hub, tmp_path, monkeypatch):
    real = torch.hub.download_url_to_file
    _offline(monkeypatch)
    cache = tmp_path / "torch" / "hub" / "checkpoints"
    for net, name in (("alex", "alexnet-owt-7be5be79.pth"), ("vgg", "vgg16-397923af.pth")):
        with pytest.raises(InputError) as e:
            load_lpips(net)
        msg = _one_line(e)
        assert msg == (f"LPIPS {net} needs {name}, which could not be downloaded (Temporary failure in name "
                       f"resolution): fetch https://download.pytorch.org/models/{name} into {cache}/ or pass "
                       "--lpips-weights FILE")
    # the lin file, when the lpips package is not installed: its own name in the same folder
    monkeypatch.setattr(torch.hub, "download_url_to_file", real)
    monkeypatch.setattr(lpips_fetch, "package_lin_file", lambda net: None)
    _serve(tmp_path, monkeypatch, "alex", _reference("alex", seed=9), lin=False)
    assert lpips_fetch.fetch_trunk("alex")[1].is_file()  # the trunk reached the cache
    _offline(monkeypatch)
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    assert _one_line(e) == (
        "LPIPS alex needs lpips_v0.1_alex-df73285e.pth, which could not be downloaded (Temporary failure in name "
        "resolution): fetch https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/"
        f"v0.1/alex.pth into {cache}/ as lpips_v0.1_alex-df73285e.pth or pass --lpips-weights FILE")


def test_an_unreachable_url_through_torch_hub_itself(hub, tmp_path, monkeypatch):
    """torch.hub's real downloader on a URL that cannot be opened: the same one line, nothing left behind."""
    url = (tmp_path / "nowhere" / "alexnet-owt-7be5be79.pth").as_uri()
    monkeypatch.setitem(lpips_fetch.TRUNK, "alex", lpips_fetch.Source(url, lpips_fetch.TRUNK["alex"].sha256))
    with pytest.raises(InputError) as e:
        load_lpips("alex")
    msg = _one_line(e)
    assert "alexnet-owt-7be5be79.pth, which could not be downloaded" in msg and url in msg
    assert list(lpips_fetch.cache_dir().iterdir()) == []


def test_a_weights_file_still_loads_as_before(hub, tmp_path, monkeypatch):
    """A full state-dict file (--lpips-weights FILE) needs no download; a file named like a network is a file
    when given as a Path (or as "./alex")."""
    sd = random_state("alex", seed=2)
    torch.save(sd, tmp_path / "alex")
    a, b = _images(2, 40, 40)
    by_str = load_lpips(str(tmp_path / "alex"))
    assert by_str.info["weights"] == str(tmp_path / "alex") and by_str.info["sha256"] == _sha(tmp_path / "alex")
    monkeypatch.chdir(tmp_path)
    assert load_lpips(__import__("pathlib").Path("alex")).distance(a, b) == by_str.distance(a, b)
    assert load_lpips("./alex").distance(a, b) == by_str.distance(a, b)
    assert hub == []
    assert lpips_unavailable_reason("alex") is None and lpips_unavailable_reason("vgg") is None
    assert "--lpips-weights" in lpips_unavailable_reason(None) and " here" not in lpips_unavailable_reason(None)
    with pytest.raises(InputError, match="no such LPIPS weights file"):
        load_lpips("squeeze")


def test_a_served_file_with_the_wrong_layout_is_refused(hub, tmp_path, monkeypatch):
    """Pinned hashes make this unreachable with the published files; with other pins every key and shape is
    still checked and named."""
    ref = _reference("alex", seed=10)
    files = _serve(tmp_path, monkeypatch, "alex", ref)
    trunk = torch.load(files["trunk"], weights_only=True)
    for name, bad, want in (("missing", {k: v for k, v in trunk.items() if k != "features.10.bias"},
                             "missing features.10.bias"),
                            ("shape", trunk | {"features.3.weight": trunk["features.3.weight"][:, :32]},
                             "features.3.weight has shape"),
                            ("vgg", {f"features.{i}.weight": torch.zeros(1) for i in (0, 2, 5)}, "missing")):
        f = tmp_path / "server" / "trunk.tmp"
        torch.save(bad, f)
        sha = _sha(f)
        f = f.rename(tmp_path / "server" / f"{name}-{sha[:8]}.pth")
        monkeypatch.setitem(lpips_fetch.TRUNK, "alex", lpips_fetch.Source(f.as_uri(), sha))
        with pytest.raises(InputError) as e:
            load_lpips("alex")
        msg = _one_line(e)
        assert want in msg and str(lpips_fetch.trunk_file("alex")) in msg, msg
