"""The residual quantizer and the action VQ-VAE: codes, EMA updates, straight-through gradients, seeded training."""

import pytest
import torch

from carp.tokenizer.kinds.chunk_vqvae import (
    ActionAutoencoder,
    AutoencoderShape,
    AutoencoderTraining,
    train_autoencoder,
)
from carp.tokenizer.kinds.residual_quantizer import ResidualVectorQuantizer

SHAPE = AutoencoderShape(
    action_horizon=4, action_dim=2, hidden_width=16, latent_width=8, num_layers=2, num_codes=4, codebook_decay=0.9
)


def initialized_quantizer(num_layers: int = 2) -> tuple[ResidualVectorQuantizer, torch.Tensor]:
    latent = torch.randn(64, 8, generator=torch.Generator().manual_seed(0))
    quantizer = ResidualVectorQuantizer(num_layers, 4, 8, decay=0.9)
    quantizer.initialize(latent, torch.Generator().manual_seed(1))
    return quantizer, latent


def test_codes_of_forward_match_encode_and_rebuild_the_quantized_latent():
    quantizer, latent = initialized_quantizer()
    quantized, code_ids, _ = quantizer.eval()(latent)
    assert code_ids.shape == (64, 2) and code_ids.dtype == torch.long
    assert torch.equal(code_ids, quantizer.encode_to_ids(latent))
    assert torch.allclose(quantized, quantizer.ids_to_latent(code_ids))


def test_second_layer_codes_the_residual_of_the_first():
    quantizer = ResidualVectorQuantizer(2, 4, 8, decay=0.9)
    coarse = 10.0 * torch.eye(8)[:4]
    fine = 0.5 * torch.eye(8)[4:]
    quantizer.codebooks.copy_(torch.stack([coarse, fine]))
    quantizer.initialized.fill_(True)
    expected = torch.cartesian_prod(torch.arange(4), torch.arange(4))  # (16, 2)
    latent = coarse[expected[:, 0]] + fine[expected[:, 1]]
    assert torch.equal(quantizer.encode_to_ids(latent), expected)
    assert torch.allclose(quantizer.ids_to_latent(expected), latent)


def test_gradients_pass_straight_through_and_codebooks_are_not_parameters():
    quantizer, latent = initialized_quantizer()
    latent = latent.clone().requires_grad_(True)
    quantized, _, _ = quantizer.eval()(latent)
    quantized.sum().backward()
    assert torch.equal(latent.grad, torch.ones_like(latent))
    assert list(quantizer.parameters()) == []


def test_ema_moves_codes_to_their_cluster_means_only_in_training_mode():
    centres = torch.tensor([[4.0, 0.0], [-4.0, 0.0]])
    points = centres.repeat_interleave(32, dim=0) + 0.1 * torch.randn(64, 2, generator=torch.Generator().manual_seed(0))
    quantizer = ResidualVectorQuantizer(1, 2, 2, decay=0.5)
    quantizer.initialize(points, torch.Generator().manual_seed(3))
    frozen = quantizer.codebooks.clone()
    quantizer.eval()(points)
    assert torch.equal(quantizer.codebooks, frozen)
    quantizer.train()
    for _ in range(40):
        quantizer(points)
    codes = quantizer.codebooks[0]
    means = torch.stack([points[:32].mean(0), points[32:].mean(0)])
    order = codes[:, 0].argsort(descending=True)
    assert torch.allclose(codes[order], means, atol=1e-3)


def test_commitment_sums_each_layers_distance_to_its_code_and_reaches_the_latent():
    quantizer = ResidualVectorQuantizer(2, 2, 1, decay=0.9)
    quantizer.codebooks.copy_(torch.tensor([[[0.0], [10.0]], [[0.0], [1.0]]]))
    quantizer.initialized.fill_(True)
    latent = torch.tensor([[10.75]], requires_grad=True)
    _, code_ids, commitment = quantizer.eval()(latent)
    # Layer 0 codes 10 (distance 0.75), layer 1 codes the residual 0.75 with 1 (distance 0.25).
    assert code_ids.tolist() == [[1, 1]]
    assert commitment.item() == pytest.approx(0.75**2 + 0.25**2)
    commitment.backward()
    assert latent.grad.item() == pytest.approx(2 * 0.75 + 2 * -0.25)


def test_the_first_layers_term_holds_the_latents_scale_where_a_loss_on_the_sum_alone_does_not():
    quantizer = ResidualVectorQuantizer(2, 2, 1, decay=0.9)
    quantizer.codebooks.copy_(torch.tensor([[[0.0], [1.0]], [[0.0], [100.0]]]))
    quantizer.initialized.fill_(True)
    # A latent far beyond the first layer's codes that the second layer codes exactly: the sum of the codes meets it,
    # so only the per-layer terms see how far it is from the coarsest codes.
    latent = torch.tensor([[101.0]])
    quantized, _, commitment = quantizer.eval()(latent)
    assert quantized.item() == pytest.approx(101.0)
    assert commitment.item() == pytest.approx(100.0**2)


def test_uninitialized_codebooks_refuse_to_quantize():
    with pytest.raises(RuntimeError, match="not initialized"):
        ResidualVectorQuantizer(2, 4, 8, decay=0.9)(torch.zeros(3, 8))


def chunks() -> torch.Tensor:
    """(64, 4, 2) smooth chunks: lines through the origin with random slopes, a structure a VQ-VAE can learn."""
    slopes = torch.rand(64, 1, 2, generator=torch.Generator().manual_seed(5)) * 2 - 1
    return slopes * torch.linspace(0, 1, 4).view(1, 4, 1)


def trained_autoencoder(seed: int, steps: int = 60) -> ActionAutoencoder:
    torch.manual_seed(0)
    autoencoder = ActionAutoencoder(SHAPE)
    train_autoencoder(autoencoder, chunks(), AutoencoderTraining(steps, 16, 3e-3, 0.0, 1.0, seed))
    return autoencoder


def test_training_is_deterministic_given_the_seed_reduces_l1_and_freezes():
    first, second, other = trained_autoencoder(0), trained_autoencoder(0), trained_autoencoder(1, steps=1)
    for name, value in first.state_dict().items():
        assert torch.equal(value, second.state_dict()[name]), name
    assert not torch.equal(first.quantizer.codebooks, other.quantizer.codebooks)
    assert not first.training and not any(p.requires_grad for p in first.parameters())
    actions = chunks()
    untrained = trained_autoencoder(0, steps=1)
    error = (first.decode_ids(first.encode_to_ids(actions)) - actions).abs().mean()
    initial = (untrained.decode_ids(untrained.encode_to_ids(actions)) - actions).abs().mean()
    assert error < 0.8 * initial
    assert first.decode_ids(first.encode_to_ids(actions)).shape == (64, 4, 2)
