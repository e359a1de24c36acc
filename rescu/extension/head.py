"""What stage II's training and the backbone fine-tuning share: the classifier head and
the deterministic torch context they are built and trained in.

:func:`make_head` builds the 3-layer head (dense, ReLU, dense, ReLU, dense to the class
scores); :func:`deterministic` seeds torch and switches its deterministic algorithms on
for the block. :mod:`rescu.extension.train`, :mod:`rescu.extension.predict` and
:mod:`rescu.extension.finetune` import them from here, so fine-tuning and the head's
training import nothing of each other. torch is imported where used: importing this module
stays free of it.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator


@contextlib.contextmanager
def deterministic(seed: int) -> Iterator[None]:
    """Seed torch (``torch.manual_seed(seed)``) and use deterministic algorithms
    (warn only) inside the block; the previous mode is restored after it."""
    import torch

    prev = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.manual_seed(int(seed))
    _set_deterministic(torch, True, warn_only=True)
    try:
        yield
    finally:
        _set_deterministic(torch, prev, warn_only=prev_warn)


def _set_deterministic(torch: Any, mode: bool, warn_only: bool) -> None:
    """``torch.use_deterministic_algorithms`` without its import of ``torch._inductor``.

    The public function also sets the compiler's (Inductor's) flag, and importing the
    compiler costs about 1.7 s per process on a 2-core machine; stage II never compiles,
    so only the eager-mode flag is set (the same C++ switch the public function sets).
    """
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:  # a torch without the private switch: the public call
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(mode, warn_only=warn_only)


def make_head(in_dim: int, hidden: tuple[int, ...], n_out: int) -> Any:
    """The classifier head: ``Linear(in_dim, hidden[0])``, ReLU, ``Linear(hidden[0],
    hidden[1])``, ReLU, ``Linear(hidden[1], n_out)`` (a ``torch.nn.Sequential``; input
    ``(B, in_dim)`` features, output ``(B, n_out)`` class scores)."""
    import torch.nn as nn

    return nn.Sequential(nn.Linear(in_dim, hidden[0]), nn.ReLU(),
                         nn.Linear(hidden[0], hidden[1]), nn.ReLU(),
                         nn.Linear(hidden[1], n_out))
