"""The successive discriminator judges every state of the chain and passes gradients to the denoiser."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from dadiff.export.config import lite_config  # noqa: E402
from dadiff.export.discriminator import SuccessiveDiscriminator, adversarial_loss, chain_timesteps  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402


def test_every_timestep_is_judged_and_gradients_reach_the_denoiser():
    torch.manual_seed(0)
    net = build_model(lite_config().with_steps(4)).train()
    disc = SuccessiveDiscriminator(64)
    out = net.template_branch(torch.rand(2, 3, 127, 127) * 255)
    states = out.states[0]
    steps = chain_timesteps(net.sampler.start_t, net.sampler.timesteps)
    assert steps == [15, 10, 5, 0, -1] and len(states) == 5
    scores = disc(states, steps)
    assert scores.shape == (2, 5)
    adversarial_loss(scores, 0.0).backward()
    assert net.diffusion.conv_in.weight.grad is not None and net.diffusion.conv_in.weight.grad.abs().sum() > 0
    assert all(p.grad is not None for p in disc.t_embed.parameters())


def test_timestep_changes_the_judgement():
    torch.manual_seed(0)
    disc = SuccessiveDiscriminator(64).eval()
    x = torch.randn(1, 64, 32, 32)
    with torch.no_grad():
        disc.t_embed.weight.normal_()
        assert not torch.allclose(disc.judge(x, 10), disc.judge(x, 0))
