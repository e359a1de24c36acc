"""Time and peak memory of the RESCU-II steps on one ~1-megapixel image.

Prints seconds and peak RSS growth for: proposals, backbone passes (image + augmented
copies, at the configured scales), pooling, training and prediction, and the time of
the plain forward passes over the image at the configured scales for comparison.

Usage::

    python benchmarks/speed/bench_stage2.py [image] [--threads 1] [--params '{"n_augment": 2}']

Without an image a 1152x864 synthetic facade (grid of textured windows) is used.
Stage-I input: a grid RP with 60 % of the windows (the rest to be found).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("image", nargs="?")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--params", default="{}")
    a = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(a.threads)
    import numpy as np
    import torch

    torch.set_num_threads(a.threads)
    from rescu.extension import backbone as B
    from rescu.extension import proposals as PR
    from rescu.extension.proposal_features import compute_stage2_features, get_backbone
    from rescu.extension.params import Stage2Params
    from rescu.extension.predict import predict_stage2
    from rescu.extension.train import train_heads
    from rescu.types import ImageResult, Instance, Pattern

    p = Stage2Params.from_dict(json.loads(a.params))
    rng = np.random.default_rng(0)
    if a.image:
        from rescu.io import load_image

        im = load_image(a.image, max_side=1152)
        rgb, sf = im.rgb, im.scale_factor
    else:
        rgb = np.full((864, 1152, 3), 170, np.uint8)
        rgb += rng.integers(0, 20, rgb.shape, dtype=np.uint8)
        tex = rng.integers(0, 255, (48, 36, 3), dtype=np.uint8)
        sf = 1.0
    h, w = rgb.shape[:2]
    boxes = []
    for y in range(40, h - 60, 90):
        for x in range(40, w - 50, 80):
            if not a.image:
                rgb[y:y + 48, x:x + 36] = tex
            boxes.append((float(x), float(y), 36.0, 48.0))
    keep = sorted(rng.choice(len(boxes), int(0.6 * len(boxes)), replace=False))
    s1 = ImageResult("bench.png", w, h, "rescu-i",
                     [Pattern(0, 1.0, [Instance(boxes[i]) for i in keep])])
    print(f"image {w}x{h} = {w * h / 1e6:.2f} MP, threads {a.threads}, "
          f"{len(keep)} stage-I instances, backbone {p.backbone.name}")
    r0 = rss_mb()
    t = time.perf_counter()
    bb = get_backbone(p)
    print(f"load backbone        {time.perf_counter() - t:7.2f} s")
    inst = np.array([boxes[i] for i in keep], np.float32) * sf
    t = time.perf_counter()
    props, _ = PR.propose(rgb, [inst], p.proposals.proposal_params())
    t_prop = time.perf_counter() - t
    print(f"proposals            {t_prop:7.2f} s   ({len(props)} boxes)")
    short = float(np.median(np.minimum(inst[:, 2], inst[:, 3])))
    pb = p.backbone
    base = (pb.instance_target_px / short if pb.instance_target_px > 0
            else min(1, pb.input_side / max(w, h)))
    base = min(base, pb.max_backbone_side / (max(w, h) * max(pb.input_scales)))
    import cv2

    t_fwd = 0.0
    for s in p.backbone.input_scales:
        img = cv2.resize(rgb, (round(w * base * s), round(h * base * s)))
        t = time.perf_counter()
        fmap = bb.feature_map(img)
        t_fwd += time.perf_counter() - t
    print(f"forward pass(es)     {t_fwd:7.2f} s   (input {img.shape[1]}x{img.shape[0]}, "
          f"map {tuple(fmap.shape)})")
    t = time.perf_counter()
    B.pool_boxes(fmap, props * base, (img.shape[1], img.shape[0]), p.backbone.pool_size)
    print(f"roi pooling          {time.perf_counter() - t:7.2f} s   ({len(props)} boxes, one map)")
    t = time.perf_counter()
    feats = compute_stage2_features(rgb, sf, s1, p)
    t_feat = time.perf_counter() - t
    print(f"features (all)       {t_feat:7.2f} s   (proposals + {1 + p.examples.n_augment} x "
          f"{len(p.backbone.input_scales)} backbone passes + pooling); backbone+pool ~ "
          f"{t_feat - t_prop:.2f} s = {(t_feat - t_prop) / max(t_fwd, 1e-9):.1f} x forward")
    t = time.perf_counter()
    ckpt, info = train_heads(feats, s1, p)
    t_train = time.perf_counter() - t
    print(f"training             {t_train:7.2f} s   ({info.get('n_examples')} examples, "
          f"{info.get('epochs')} epochs)")
    t = time.perf_counter()
    out = predict_stage2(feats, ckpt, s1, p)
    t_pred = time.perf_counter() - t
    print(f"prediction           {t_pred:7.2f} s   ({out.extra['stage2']['added']} added)")
    print(f"stage II total       {t_feat + t_train + t_pred:7.2f} s")
    print(f"peak RSS             {rss_mb():7.0f} MB (+{rss_mb() - r0:.0f} MB during stage II)")


if __name__ == "__main__":
    main()
