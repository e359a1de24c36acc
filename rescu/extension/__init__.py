"""Stage II (RESCU-II, paper section 4): self-supervised extension of each recurring
pattern (RP) with a CNN.

Stage I misses instances (blur, occlusion, few SIFT features). Stage II learns, from
stage I's own output and nothing else, what an instance of each RP looks like and finds
the missing ones. Three per-image steps (three pipeline rules):

1. :func:`proposal_features.compute_stage2_features` — region proposals (EdgeBoxes and/or
   windows at the RP's instance scale, :mod:`rescu.extension.proposals`) and frozen ImageNet features
   (:mod:`rescu.extension.backbone`) of the proposals, of the stage-I instances, of geometrically
   deformed instance boxes and of hard negatives, in the image and in ``n_augment``
   globally transformed copies of it.
2. :func:`train.train_heads` — self-supervised labels: DBSCAN on the features of each RP's
   instances gives cluster centres; the ``top k = N x P`` proposals nearest to the N
   centres (P = ``top_p`` = 40, capped at ``max_positive_fraction`` of the proposals)
   are positives together with the stage-I instances; proposals far from all centres are
   negatives. A classifier of 3 dense layers on the frozen features (one head per image,
   softmax over one class per RP + background) is trained with cross-entropy, Adam
   (lr 1e-4, beta1 0.5), batch 32, at most 20 epochs, 20 % validation split, early
   stopping when the validation loss does not improve by 5e-4 in 3 epochs.
3. :func:`predict.predict_stage2` — the classifier's positive proposals of each RP (score
   threshold, size gate, NMS among themselves and against the stage-I instances) merged
   with the stage-I instances are the RESCU-II instances.

Departures from the paper (documented, environment-driven):

* Frozen backbone, one pass per image / input scale / augmented copy, box features
  RoI-pooled from the shared map (no per-crop passes). ``finetune=True`` trains the
  backbone end to end first (:mod:`rescu.extension.finetune`; meant for a CUDA GPU, slow on a
  CPU) and pools every feature from the fine-tuned backbone.
* Augmentation happens on the image copies (global: horizontal flip, rescale,
  brightness/contrast, blur) passed once each; the "local geometric deformation driven by
  the RP instances" is a random shift/scale of each instance box by at most
  ``jitter`` times the spread of the RP's instance sizes (at least ``min_jitter`` of the
  size), pooled from the same maps.
* Local appearance deformation is optional (``occlude_prob``, off by default): random
  occluders over part of the instances in the augmented copies (random erasing,
  :func:`augment.occlude_instances`). The paper's version is not specified further.
* Partly hidden instances (optional, ``visible_half``, off by default): a lattice window
  is also scored with one half of its pooled grid (left, right, top or bottom) kept and
  the other half replaced by the RP's mean instance feature
  (:func:`predict.visible_half_features`), so an instance whose visible half looks right can pass
  the lattice gate; only for windows inside the span of the RP's instances
  (interpolation, not extrapolation past a row's end). Not in the paper.
* Hard negatives: each instance box shifted by half its size, and doubled in size.
* A size gate: a proposal can only be an instance of an RP when its width and height are
  within a factor ``size_tolerance`` of those of one of its stage-I instances (the paper's
  proposals pass a classifier trained on crops resized to the input size and carry no
  size information; here the pooled features do not separate scale well).

Modules: ``params`` (:class:`params.Stage2Params`, the prediction-only keys), ``proposals``
(region proposals), ``backbone`` (frozen CNN features of boxes), ``finetune`` (optional
backbone fine-tuning), ``augment`` (image copies, occluders, box jitter, hard negatives),
``proposal_features`` (step 1), ``examples`` (DBSCAN centres, positives and negatives),
``head`` (the classifier head and the deterministic torch
context), ``optim`` (Adam without TorchDynamo), ``train`` (step 2), ``predict`` (step 3)
and ``merge`` (joining RPs of one pattern); box geometry and suppression are
:mod:`rescu.boxes`. Nothing is imported here.
"""
