"""End-to-end fine-tuning of the stage-II backbone (``stage2.finetune: true``).

The paper trains "the backbone + 3 dense layers" per image. The default pipeline keeps
the backbone frozen and trains only the dense head on RoI-pooled features of one shared
feature map per image (far cheaper on a CPU; see :mod:`rescu.extension.proposal_features`). With
``finetune: true`` the backbone is trained too, on the same labelled boxes (stage-I
instances, their deformed copies and the positive proposals of each RP; hard negatives
and far proposals as background):

* every step runs the backbone on the whole image (at the backbone scale of the cached
  features) with gradients, RoI-aligns the features of a batch of boxes from that map,
  L2-normalises them and classifies them with a temporary head of the configured dense
  layers (softmax over ``R + 1`` classes, background = 0);
* cross-entropy (class-balanced), Adam (``lr``, ``beta1``), ``batch_size`` boxes per step,
  at most ``max_epochs`` epochs, ``val_split`` of the boxes held out, early stopping when
  the validation loss does not improve by ``min_delta`` in ``patience`` epochs — the
  paper's schedule;
* batch-norm statistics stay frozen (one image per step: batch statistics would be
  meaningless), every convolution is trained.

The fine-tuned backbone then re-computes the cached features of every box, and the head
of :func:`rescu.extension.train.train_heads` is trained on those as usual. Meant for a CUDA GPU
(``stage2.device: cuda``); it runs on a CPU as well, slowly (one full backbone pass per
step).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from .backbone import FrozenBackbone, box_rois
from .head import deterministic, make_head


def _scaled(rgb: np.ndarray, scale: float) -> tuple[np.ndarray, float, float]:
    import cv2

    h, w = rgb.shape[:2]
    nw, nh = max(16, int(round(w * scale))), max(16, int(round(h * scale)))
    if (nw, nh) == (w, h):
        return rgb, 1.0, 1.0
    img = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA if scale < 1
                     else cv2.INTER_LINEAR)
    return img, nw / w, nh / h


def finetune_backbone(backbone: FrozenBackbone, rgb: np.ndarray, boxes: np.ndarray,
                      labels: np.ndarray, n_classes: int, *, scale: float = 1.0,
                      pool_size: int = 2, hidden_sizes: tuple[int, ...] = (256, 128),
                      lr: float = 1e-4, beta1: float = 0.5, batch_size: int = 32,
                      max_epochs: int = 20, val_split: float = 0.2, patience: int = 3,
                      min_delta: float = 5e-4, seed: int = 0
                      ) -> tuple[FrozenBackbone, dict[str, Any]]:
    """Fine-tune a copy of ``backbone`` end to end to classify ``boxes``.

    Parameters
    ----------
    backbone : FrozenBackbone
        The frozen backbone (left unchanged).
    rgb : (H, W, 3) uint8
        The processed image.
    boxes : (N, 4) float
        Labelled boxes ``[x, y, w, h]`` in pixels of ``rgb``.
    labels : (N,) int
        Class of each box in ``0 .. n_classes - 1`` (0 = background, k + 1 = RP k).
    n_classes : int
        Number of classes (>= 2).
    scale : float
        ``rgb`` is resized by this before the backbone (the backbone scale of the cached
        features), > 0.
    pool_size, hidden_sizes, lr, beta1, batch_size, max_epochs, val_split, patience,
    min_delta, seed
        As in :class:`rescu.extension.params.Stage2Params`.

    Returns
    -------
    backbone : FrozenBackbone
        A fine-tuned copy (eval mode, no gradients), usable wherever the frozen one is.
    info : dict
        ``status`` ("finetuned" or "skipped" with ``reason``), ``epochs``,
        ``train_loss``/``val_loss`` per epoch, ``best_val_loss``, ``n_boxes``, ``device``.
    """
    import torch
    from torchvision.ops import roi_align

    b = np.asarray(boxes, np.float32).reshape(-1, 4)
    y = np.asarray(labels, np.int64).reshape(-1)
    if len(b) != len(y):
        raise ValueError(f"boxes ({len(b)}) and labels ({len(y)}) must have the same length")
    if n_classes < 2:
        raise ValueError(f"n_classes must be >= 2, got {n_classes}")
    if len(y) and (y.min() < 0 or y.max() >= n_classes):
        raise ValueError(f"labels must be in 0..{n_classes - 1}")
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")
    dev = backbone.device
    info: dict[str, Any] = {"n_boxes": int(len(y)), "device": str(dev)}
    if len(y) < 4 or len(np.unique(y)) < 2:
        return backbone, dict(info, status="skipped", reason="fewer than 4 boxes or one class")

    img, fx, fy = _scaled(np.asarray(rgb), scale)
    bs = b * np.array([fx, fy, fx, fy], np.float32)
    H, W = img.shape[:2]
    x_img = backbone.preprocess(img)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(y))
    n_val = int(round(val_split * len(y))) if len(y) >= 10 else 0
    val, tr = perm[:n_val], perm[n_val:]
    counts = np.bincount(y[tr], minlength=n_classes).astype(np.float64)
    w = np.where(counts > 0, len(tr) / (n_classes * np.maximum(counts, 1)), 0.0)

    tuned = copy.copy(backbone)
    with deterministic(seed):
        tuned.model = copy.deepcopy(backbone.model)
        for p in tuned.model.parameters():
            p.requires_grad_(True)
        tuned.model.eval()  # frozen batch-norm statistics (one image per step)
        d = tuned.channels * pool_size * pool_size
        head = make_head(d, tuple(hidden_sizes), n_classes).to(dev)
        params = list(tuned.model.parameters()) + list(head.parameters())
        opt = torch.optim.Adam(params, lr=lr, betas=(beta1, 0.999))
        lossf = torch.nn.CrossEntropyLoss(weight=torch.tensor(w, dtype=torch.float32,
                                                              device=dev))

        def logits(idx: np.ndarray) -> Any:
            fmap = tuned.forward_tensor(x_img)
            rois = box_rois(bs[idx], (int(fmap.shape[2]), int(fmap.shape[3])), (W, H))
            r = roi_align(fmap, torch.from_numpy(rois).to(dev), (pool_size, pool_size),
                          spatial_scale=1.0, sampling_ratio=2, aligned=True)
            f = r.reshape(len(idx), -1)
            f = f / f.norm(dim=1, keepdim=True).clamp_min(1e-12)
            return head(f)

        yt = torch.from_numpy(y).to(dev)
        best, best_state, bad = np.inf, None, 0
        hist_tr: list[float] = []
        hist_val: list[float] = []
        for _ in range(int(max_epochs)):
            head.train()
            order = tr[rng.permutation(len(tr))]
            tot = 0.0
            for i in range(0, len(order), batch_size):
                idx = order[i:i + batch_size]
                opt.zero_grad()
                loss = lossf(logits(idx), yt[torch.from_numpy(idx).to(dev)])
                loss.backward()
                opt.step()
                tot += float(loss.detach()) * len(idx)
            hist_tr.append(tot / max(1, len(order)))
            head.eval()
            ev = val if len(val) else tr
            with torch.no_grad():
                vl = 0.0
                for i in range(0, len(ev), 256):
                    idx = ev[i:i + 256]
                    vl += float(lossf(logits(idx), yt[torch.from_numpy(idx).to(dev)])) * len(idx)
                vl /= max(1, len(ev))
            hist_val.append(vl)
            if vl < best - min_delta:
                best, bad = vl, 0
                best_state = {k: v.detach().clone() for k, v in tuned.model.state_dict().items()}
            else:
                bad += 1
                if bad >= patience:
                    break
    assert best_state is not None
    tuned.model.load_state_dict(best_state)
    for p in tuned.model.parameters():
        p.requires_grad_(False)
    tuned.model.eval()
    info.update(status="finetuned", epochs=len(hist_tr), best_val_loss=float(best),
                train_loss=[round(v, 6) for v in hist_tr],
                val_loss=[round(v, 6) for v in hist_val])
    return tuned, info
