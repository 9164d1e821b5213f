"""km.torch: a rollout as a torch autograd function (on the NumPy test simulation of
tests/diff_toy.py): gradients equal km.diff's, flow through chained calls and into a torch
controller, and agree with finite differences."""

import numpy as np
import pytest

from diff_toy import Oscillators

torch = pytest.importorskip("torch")
import kinema as km  # noqa: E402


def make():
    rng = np.random.default_rng(3)
    return Oscillators(rng.normal(size=(4, 2)), rng.normal(size=(4, 2)))


def test_gradients_equal_km_diff():
    w = torch.linspace(-1, 1, 8, dtype=torch.float64).reshape(4, 2)
    v0 = torch.tensor(make().v, requires_grad=True)
    k = torch.tensor(3.0, dtype=torch.float64, requires_grad=True)
    out = km.torch.rollout(make(), 20, 0.02, {"v": v0, "stiffness": k})
    loss = (w * out["x"]).sum() + (out["v"] ** 2).sum()
    loss.backward()
    run = km.diff.rollout(make(), 20, 0.02, wrt=("v", "stiffness"))
    ref = run.backward({"x": w.numpy(), "v": 2 * run.outputs["v"]})
    np.testing.assert_array_equal(v0.grad.numpy(), ref["v"])
    assert k.grad.item() == ref["stiffness"]


def test_chained_one_step_calls_with_a_torch_controller_match_finite_differences():
    # A linear feedback controller u_k = W x_k, its weight learned through 15 one-step calls.
    torch.manual_seed(0)
    W = (0.1 * torch.randn(2, 2, dtype=torch.float64)).requires_grad_(True)

    def loss_of(W):
        sim = make()
        x, v = torch.tensor(sim.x), torch.tensor(sim.v)
        for _ in range(15):
            u = (x @ W.T).unsqueeze(0)
            out = km.torch.rollout(sim, 1, 0.05, {"x": x, "v": v}, controls=u)
            x, v = out["x"], out["v"]
        return (x ** 2).sum()

    loss_of(W).backward()
    direction = torch.randn(2, 2, dtype=torch.float64)
    eps = 1e-6  # central difference error ~ eps^2 |L'''| ~ 1e-12, rounding ~ 1e-16 / eps = 1e-10
    with torch.no_grad():
        fd = (loss_of(W + eps * direction) - loss_of(W - eps * direction)) / (2 * eps)
    ad = (W.grad * direction).sum()
    assert abs(ad.item() - fd.item()) <= 1e-7 * max(1.0, abs(fd.item())), (ad.item(), fd.item())


def test_no_gradient_inputs_run_forward_only():
    sim, plain = make(), make()
    out = km.torch.rollout(sim, 5, 0.1, {"v": torch.tensor(sim.v)})
    for _ in range(5):
        plain.step(0.1)
    np.testing.assert_array_equal(out["x"].numpy(), plain.x)
    assert not out["x"].requires_grad


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="inputs: unknown name 'q'"):
        km.torch.rollout(make(), 2, 0.1, {"q": torch.zeros(1)})
    with pytest.raises(ValueError, match=r"inputs\['v'\]: expected a torch.Tensor"):
        km.torch.rollout(make(), 2, 0.1, {"v": np.zeros((4, 2))})
    with pytest.raises(ValueError, match="outputs: unknown name"):
        km.torch.rollout(make(), 2, 0.1, {}, outputs=("w",))
    with pytest.raises(ValueError, match="dt"):
        km.torch.rollout(make(), 2, -1.0, {})
