"""Adam for stage II's small heads, without the start-up cost of ``torch.optim``.

``torch.optim``'s optimizers import the TorchDynamo compiler on their first call (about
1 s per process on a 2-core machine, more than training a stage-II head takes).
:class:`Adam` does the same arithmetic as ``torch.optim.Adam`` with its defaults on CPU
(the single-tensor update, no weight decay, no AMSGrad), kernel for kernel (torch's
``_foreach_`` operations over the parameters, which on CPU run the single-tensor kernels
one tensor after the other), so the trained weights are bit-identical;
``tests/test_optim.py`` checks that against ``torch.optim.Adam``.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


class Adam:
    """Adam (Kingma & Ba) over a fixed list of parameters.

    Parameters
    ----------
    params : iterable of torch.Tensor
        Leaf tensors with ``requires_grad``; updated in place by :meth:`step`.
    lr : float
        Learning rate (> 0).
    betas : (float, float)
        Decay of the first and second moment estimates, each in [0, 1).
    eps : float
        Added to the denominator (> 0).
    """

    def __init__(self, params: Iterable[Any], lr: float = 1e-3,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        import torch

        self.params = list(params)
        if not lr > 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if not (0 <= betas[0] < 1 and 0 <= betas[1] < 1):
            raise ValueError(f"betas must lie in [0, 1), got {betas}")
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.lr, self.beta1, self.beta2, self.eps = float(lr), float(betas[0]), \
            float(betas[1]), float(eps)
        self._torch = torch
        self._state: list[dict[str, Any] | None] = [None] * len(self.params)

    def zero_grad(self) -> None:
        """Drop every parameter's gradient (``set_to_none``, as ``torch.optim``)."""
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        """One update of every parameter that has a gradient.

        The parameters that share a step count are updated together with torch's
        ``_foreach_`` operations, which on CPU run the same per-tensor kernels as the
        single-tensor update in one call instead of eight per parameter (the same floats;
        a stage-II head takes a few thousand steps)."""
        torch = self._torch
        b1, b2 = self.beta1, self.beta2
        with torch.no_grad():
            groups: dict[int, list[int]] = {}
            for i, p in enumerate(self.params):
                if p.grad is None:
                    continue
                st = self._state[i]
                if st is None:
                    st = self._state[i] = {
                        "step": 0,
                        "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                        "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
                st["step"] += 1
                groups.setdefault(st["step"], []).append(i)
            for step, idx in groups.items():
                params = [self.params[i] for i in idx]
                grads = [p.grad for p in params]
                avgs = [self._state[i]["exp_avg"] for i in idx]  # type: ignore[index]
                sqs = [self._state[i]["exp_avg_sq"] for i in idx]  # type: ignore[index]
                torch._foreach_lerp_(avgs, grads, 1 - b1)
                torch._foreach_mul_(sqs, b2)
                torch._foreach_addcmul_(sqs, grads, grads, value=1 - b2)
                # torch.optim.Adam's step is a float32 tensor read back as a float: the
                # same integer as a Python float
                bias_correction1 = 1 - b1 ** float(step)
                bias_correction2 = 1 - b2 ** float(step)
                step_size = self.lr / bias_correction1
                denom = torch._foreach_sqrt(sqs)
                torch._foreach_div_(denom, bias_correction2 ** 0.5)
                torch._foreach_add_(denom, self.eps)
                torch._foreach_addcdiv_(params, avgs, denom, value=-step_size)
