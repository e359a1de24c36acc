"""End-to-end fine-tuning of the stage-II backbone (rescu.extension.finetune), tiny image, CPU."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rescu.extension import backbone as B  # noqa: E402
from rescu.extension.finetune import finetune_backbone  # noqa: E402


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 160x128 image: four textured squares (class 1) on noise (class 0 boxes)."""
    rng = np.random.default_rng(0)
    img = rng.integers(90, 110, (128, 160, 3)).astype(np.uint8)
    tex = rng.integers(0, 255, (24, 24, 3)).astype(np.uint8)
    pos = []
    for k in range(4):
        x, y = 10 + 36 * k, 20
        img[y:y + 24, x:x + 24] = tex
        pos.append([x, y, 24, 24])
    neg = [[10 + 36 * k, 80, 24, 24] for k in range(4)]
    boxes = np.array(pos + neg, np.float32)
    labels = np.array([1] * 4 + [0] * 4)
    return img, boxes, labels


def test_finetune_changes_weights_and_keeps_the_original() -> None:
    torch.set_num_threads(1)
    img, boxes, labels = _scene()
    frozen = B.FrozenBackbone("efficientnet-lite0")
    before = {k: v.clone() for k, v in frozen.model.state_dict().items()}
    tuned, info = finetune_backbone(frozen, img, boxes, labels, 2, max_epochs=2,
                                    batch_size=4, lr=1e-3, seed=0)
    assert info["status"] == "finetuned" and info["epochs"] >= 1
    assert len(info["train_loss"]) == info["epochs"]
    # the frozen backbone is untouched, the copy differs and is frozen again
    after = frozen.model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert any(not torch.equal(before[k], v) for k, v in tuned.model.state_dict().items()
               if v.dtype.is_floating_point)
    assert not any(p.requires_grad for p in tuned.model.parameters())
    f = B.pool_boxes(tuned.feature_map(img), boxes, (160, 128))
    assert f.shape == (8, tuned.channels * 4) and np.isfinite(f).all()


def test_finetune_is_deterministic_and_checks_input() -> None:
    torch.set_num_threads(1)
    img, boxes, labels = _scene()
    frozen = B.FrozenBackbone("efficientnet-lite0")
    a, _ = finetune_backbone(frozen, img, boxes, labels, 2, max_epochs=1, batch_size=4, seed=3)
    b, _ = finetune_backbone(frozen, img, boxes, labels, 2, max_epochs=1, batch_size=4, seed=3)
    fa = B.pool_boxes(a.feature_map(img), boxes, (160, 128))
    fb = B.pool_boxes(b.feature_map(img), boxes, (160, 128))
    assert np.array_equal(fa, fb)
    same, info = finetune_backbone(frozen, img, boxes[:4], labels[:4], 2)
    assert same is frozen and info["status"] == "skipped"
    with pytest.raises(ValueError, match="same length"):
        finetune_backbone(frozen, img, boxes, labels[:3], 2)
    with pytest.raises(ValueError, match="labels must be in"):
        finetune_backbone(frozen, img, boxes, labels + 5, 2)
