"""rescu.extension.optim.Adam: bit-identical to torch.optim.Adam's defaults on CPU."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rescu.extension.optim import Adam  # noqa: E402


def _train(make_opt, steps: int = 60) -> list:
    torch.manual_seed(3)
    net = torch.nn.Sequential(torch.nn.Linear(7, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3))
    frozen = torch.nn.Linear(2, 2)  # a parameter that never gets a gradient
    opt = make_opt(list(net.parameters()) + list(frozen.parameters()))
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.normal(size=(40, 7)).astype(np.float32))
    y = torch.from_numpy(rng.integers(0, 3, 40))
    lossf = torch.nn.CrossEntropyLoss(weight=torch.tensor([1.0, 2.0, 0.5]))
    for k in range(steps):
        b = torch.from_numpy(rng.permutation(40)[:8])
        opt.zero_grad()
        lossf(net(x[b]), y[b]).backward()
        opt.step()
    return [p.detach().clone() for p in list(net.parameters()) + list(frozen.parameters())]


@pytest.mark.parametrize("lr,betas", [(1e-4, (0.5, 0.999)), (3e-3, (0.9, 0.99))])
def test_adam_matches_torch_bit_for_bit(lr, betas):
    ours = _train(lambda ps: Adam(ps, lr=lr, betas=betas))
    ref = _train(lambda ps: torch.optim.Adam(ps, lr=lr, betas=betas))
    for a, b in zip(ours, ref):
        assert torch.equal(a, b)


def test_parameters_without_a_gradient_keep_their_own_step_count():
    # one layer takes part only in every third step: its step count falls behind the
    # others', so the update runs as two groups of parameters; still torch's floats
    def run(make_opt):
        torch.manual_seed(5)
        a, b = torch.nn.Linear(4, 6), torch.nn.Linear(6, 2)
        side = torch.nn.Linear(4, 2)
        opt = make_opt(list(a.parameters()) + list(b.parameters()) + list(side.parameters()))
        rng = np.random.default_rng(1)
        x = torch.from_numpy(rng.normal(size=(30, 4)).astype(np.float32))
        for k in range(40):
            opt.zero_grad()
            out = b(torch.relu(a(x)))
            if k % 3 == 0:
                out = out + side(x)
            out.square().mean().backward()
            opt.step()
        return [p.detach().clone() for m in (a, b, side) for p in m.parameters()]

    ours = run(lambda ps: Adam(ps, lr=2e-3, betas=(0.5, 0.999)))
    ref = run(lambda ps: torch.optim.Adam(ps, lr=2e-3, betas=(0.5, 0.999)))
    for x, y in zip(ours, ref):
        assert torch.equal(x, y)


def test_bad_hyperparameters():
    p = [torch.zeros(2, requires_grad=True)]
    with pytest.raises(ValueError, match="lr"):
        Adam(p, lr=0)
    with pytest.raises(ValueError, match="betas"):
        Adam(p, betas=(1.0, 0.9))
    with pytest.raises(ValueError, match="eps"):
        Adam(p, eps=0)
