"""Step 2 of RESCU-II: :func:`train_heads` — the training set from the self-supervised
examples and the per-image classifier head trained on the cached features; the head's
checkpoint file (:func:`save_checkpoint`, :func:`load_checkpoint`).

The checkpoint holds the head's weights as NumPy arrays and the example selection the
head was trained from (:func:`rescu.extension.examples.select_examples`), in HDF5:
prediction (:mod:`rescu.extension.predict`) and its variants read both and need neither
torch nor the selection again.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ..types import ImageResult
from .examples import select_examples
from .proposal_features import to_str
from .head import deterministic, make_head
from .params import Stage2Params


def _training_set(feats: dict[str, np.ndarray], sel: dict[str, Any], params: Stage2Params,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Stack the labelled examples: (X (E, D) float32, y (E,) int64)."""
    xs, ys = [], []
    inst_rp = np.asarray(feats["instance_rp"], np.int64)
    parent = np.asarray(feats["jitter_parent"], np.int64)
    lab = sel["proposal_label"]

    def add(x: np.ndarray, y: np.ndarray) -> None:
        x = np.asarray(x, np.float32).reshape(len(y), -1) if len(y) else None
        if x is not None:
            xs.append(x)
            ys.append(np.asarray(y, np.int64))

    # positives: stage-I instances, deformed boxes, positive proposals (+ augmented copies)
    add(feats["instance_features"], inst_rp + 1)
    add(feats["jitter_features"], inst_rp[parent] + 1)
    pos = np.nonzero(lab > 0)[0]
    add(np.asarray(feats["proposal_features"])[pos], lab[pos])
    A = np.asarray(feats["aug_instance_features"]).shape[0]
    aidx = np.asarray(feats["aug_proposal_index"], np.int64)
    for a in range(A):
        add(np.asarray(feats["aug_instance_features"])[a], inst_rp + 1)
        add(np.asarray(feats["aug_jitter_features"])[a], inst_rp[parent] + 1)
        sub = np.nonzero(lab[aidx] > 0)[0]
        add(np.asarray(feats["aug_proposal_features"])[a][sub], lab[aidx][sub])
    n_pos = sum(len(y) for y in ys)
    # negatives: hard negatives (+ aug), far proposals (+ aug subset), sampled
    nx = []
    hn = np.asarray(feats["hard_negative_features"], np.float32)
    if len(hn):
        nx.append(hn)
    for a in range(A):
        ah = np.asarray(feats["aug_hard_negative_features"])[a]
        if len(ah):
            nx.append(ah)
        sub = np.nonzero(lab[aidx] == 0)[0]
        if len(sub):
            nx.append(np.asarray(feats["aug_proposal_features"])[a][sub])
    negp = np.nonzero(lab == 0)[0]
    if len(negp):
        nx.append(np.asarray(feats["proposal_features"], np.float32)[negp])
    if nx:
        N = np.concatenate(nx)
        n_want = int(np.ceil(params.examples.negatives_per_positive * max(n_pos, 1)))
        if len(N) > n_want:
            N = N[np.sort(rng.choice(len(N), n_want, replace=False))]
        add(N, np.zeros(len(N), np.int64))
    if not xs:
        return np.zeros((0, 0), np.float32), np.zeros((0,), np.int64)
    return np.concatenate(xs), np.concatenate(ys)


def train_heads(feats: dict[str, np.ndarray], stage1: ImageResult,
                params: Stage2Params = Stage2Params()) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train the per-image classifier on cached features (step 2 of RESCU-II).

    One head per image: 3 dense layers, softmax over ``R + 1`` classes (background = 0,
    RP k = k + 1, k indexing ``feats["rp_index"]``). Inputs are standardised with the
    training-set mean and std (stored in the checkpoint).

    Parameters
    ----------
    feats : dict
        Output of :func:`rescu.extension.proposal_features.compute_stage2_features` (or its HDF5
        round trip).
    stage1 : ImageResult
        Stage-I result (only checked for consistency with ``feats``).
    params : Stage2Params

    Returns
    -------
    ckpt : dict
        ``state_dict`` (layer name -> float32 array, torch's names and shapes: ``"0.weight"``
        (H1, D), ``"0.bias"`` (H1,), ... ``"4.weight"`` (R + 1, H2); empty when there is
        nothing to learn), ``mean``/``std`` float32 (D,), ``in_dim``, ``hidden_sizes``,
        ``n_classes``, ``rp_index`` list, ``backbone`` str and, once examples were
        selected, ``selection`` (``distance`` (P, R) and ``radius`` (R,) of
        :func:`rescu.extension.examples.select_examples`). Save with
        :func:`save_checkpoint`.
    info : dict
        ``status`` ("trained", "no_rp", "no_examples"), ``epochs``, ``best_val_loss``,
        ``train_loss``/``val_loss`` per epoch, example counts, ``n_centres``.
    """
    import torch

    from .optim import Adam

    rp_index = [int(v) for v in np.asarray(feats["rp_index"]).reshape(-1)]
    backbone = to_str(feats["backbone"])
    for i in rp_index:
        if i >= len(stage1.patterns) or len(stage1.patterns[i].instances) < 2:  # noqa
            raise ValueError(f"feats['rp_index'] names pattern {i}, which stage1 "
                             f"({stage1.image}) does not have with >= 2 instances")
    base: dict[str, Any] = {
        "state_dict": {}, "mean": np.zeros(0, np.float32), "std": np.ones(0, np.float32),
        "in_dim": 0, "hidden_sizes": list(params.head.hidden_sizes),
        "n_classes": len(rp_index) + 1, "rp_index": rp_index, "backbone": backbone}
    if not rp_index:
        return base, {"status": "no_rp", "backbone": backbone}
    rng = np.random.default_rng(params.seed)
    sel = select_examples(feats, params)
    base["selection"] = {"distance": np.asarray(sel["distance"], np.float64),
                         "radius": np.asarray(sel["radius"], np.float64)}
    X, y = _training_set(feats, sel, params, rng)
    info: dict[str, Any] = {
        "backbone": backbone, "n_centres": sel["n_centres"].tolist(),
        "n_positive_proposals": sel["n_positive"].tolist(),
        "n_negative_proposals": int(sel["n_negative"]),
        "n_proposals": int(len(sel["proposal_label"])),
        "n_examples": int(len(y)), "n_positive_examples": int((y > 0).sum()),
    }
    if len(y) == 0 or (y == 0).sum() == 0:
        info["status"] = "no_examples"
        return base, info
    mean = X.mean(0)
    std = X.std(0) + 1e-3
    Xs = (X - mean) / std
    perm = rng.permutation(len(y))
    n_val = int(round(params.head.val_split * len(y))) if len(y) >= 10 else 0
    val, tr = perm[:n_val], perm[n_val:]
    n_cls = len(rp_index) + 1
    counts = np.bincount(y[tr], minlength=n_cls).astype(np.float64)
    w = np.where(counts > 0, len(tr) / (n_cls * np.maximum(counts, 1)), 0.0)
    with deterministic(params.seed):
        head = make_head(X.shape[1], tuple(params.head.hidden_sizes), n_cls)
        opt = Adam(head.parameters(), lr=params.head.lr, betas=(params.head.beta1, 0.999))
        lossf = torch.nn.CrossEntropyLoss(weight=torch.tensor(w, dtype=torch.float32))
        Xt = torch.from_numpy(Xs.astype(np.float32))
        yt = torch.from_numpy(y)
        best, best_state, bad, hist_tr, hist_val = np.inf, None, 0, [], []
        for ep in range(int(params.head.max_epochs)):
            head.train()
            order = tr[rng.permutation(len(tr))]
            tot = 0.0
            for i in range(0, len(order), params.head.batch_size):
                b = torch.from_numpy(order[i:i + params.head.batch_size])
                opt.zero_grad()
                loss = lossf(head(Xt[b]), yt[b])
                loss.backward()
                opt.step()
                tot += float(loss.detach()) * len(b)
            hist_tr.append(tot / max(1, len(order)))
            head.eval()
            with torch.no_grad():
                ev = val if len(val) else tr
                vl = float(lossf(head(Xt[torch.from_numpy(ev)]), yt[torch.from_numpy(ev)]))
            hist_val.append(vl)
            if vl < best - params.head.min_delta:
                best, bad = vl, 0
                best_state = {k: v.detach().numpy().astype(np.float32)
                              for k, v in head.state_dict().items()}
            else:
                bad += 1
                if bad >= params.head.patience:
                    break
    assert best_state is not None
    ckpt = dict(base, state_dict=best_state, mean=mean.astype(np.float32),
                std=std.astype(np.float32), in_dim=int(X.shape[1]))
    info.update(status="trained", epochs=len(hist_tr), best_val_loss=float(best),
                train_loss=[round(v, 6) for v in hist_tr], val_loss=[round(v, 6) for v in hist_val])
    return ckpt, info


def save_checkpoint(path: str | os.PathLike[str], ckpt: dict[str, Any]) -> None:
    """Write a checkpoint (``{"head": train_heads' ckpt, "info": its record}``, or
    ``{"failure": record}``) to HDF5 atomically, bytes depending only on the content.

    Arrays and nested mappings are stored as datasets and groups; the other values
    (numbers, strings, lists, the records) as JSON in the root's ``json`` attribute.
    """
    import json

    from ..io import write_h5

    arrays: dict[str, Any] = {}
    plain: dict[str, Any] = {}

    def split(d: dict[str, Any], arr: dict[str, Any], js: dict[str, Any]) -> None:
        for k, v in d.items():
            if isinstance(v, np.ndarray):
                arr[k] = v
            elif isinstance(v, dict) and v and all(isinstance(x, np.ndarray)
                                                   for x in v.values()):
                arr[k] = dict(v)
            elif isinstance(v, dict):
                sub_a: dict[str, Any] = {}
                sub_j: dict[str, Any] = {}
                split(v, sub_a, sub_j)
                if sub_a:
                    arr[k] = sub_a
                js[k] = sub_j
            else:
                js[k] = v

    split(ckpt, arrays, plain)
    write_h5(path, arrays, attrs={"json": json.dumps(plain, sort_keys=True)})


def load_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (arrays as NumPy arrays). A
    missing or unreadable file raises :class:`rescu.io.InputError` naming it."""
    import json

    from ..io import InputError, read_h5

    if not os.path.isfile(path):
        raise InputError(f"{path}: file not found")
    arrays, attrs = read_h5(path)
    try:
        plain = json.loads(attrs["json"])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: not a stage-II checkpoint ({type(e).__name__}: {e})") \
            from None

    def merge(js: dict[str, Any], arr: dict[str, Any]) -> dict[str, Any]:
        out = dict(js)
        for k, v in arr.items():
            out[k] = merge(js.get(k, {}), v) if isinstance(v, dict) and isinstance(
                js.get(k), dict) else v
        return out

    return merge(plain, arrays)
