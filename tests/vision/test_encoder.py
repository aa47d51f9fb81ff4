import pytest
import torch
from torch import nn

from carp.config import ConfigError
from carp.vision import ImageEncoder, ImageEncoderConfig
from carp.vision.crop import ImageCrop, center_crop, random_crop
from carp.vision.keypoints import SpatialSoftmax
from carp.vision.resnet import ResNetTrunk

# torchvision's resnet18 has 11,689,512 parameters, of which its 512 -> 1000 classifier holds 513,000.
RESNET18_TRUNK_PARAMETERS = 11_176_512


def _count(module: nn.Module) -> int:
    return sum(parameter.numel() for parameter in module.parameters())


def test_resnet18_trunk_has_the_standard_parameter_count_with_groupnorm_as_with_batchnorm():
    trunk = ResNetTrunk(64)
    assert _count(trunk) == RESNET18_TRUNK_PARAMETERS
    norms = [(name, module) for name, module in trunk.named_modules() if isinstance(module, nn.GroupNorm)]
    assert len(norms) == 20  # stem, 2 per block, 1 per projection shortcut (3)
    assert all(module.num_groups == module.num_channels // 16 for _, module in norms)
    for name, module in norms:
        parent_name, _, attribute = name.rpartition(".")
        setattr(trunk.get_submodule(parent_name), attribute, nn.BatchNorm2d(module.num_channels))
    assert _count(trunk) == RESNET18_TRUNK_PARAMETERS


def test_light_trunk_size():
    assert _count(ResNetTrunk(16)) == 702_096


def test_resnet18_layer_shapes_on_a_76_pixel_crop():
    trunk = ResNetTrunk(64)
    features = trunk.stem(torch.zeros(2, 3, 76, 76))
    assert features.shape == (2, 64, 19, 19)
    shapes = []
    for stage in trunk.stages:
        features = stage(features)
        shapes.append(tuple(features.shape))
    assert shapes == [(2, 64, 19, 19), (2, 128, 10, 10), (2, 256, 5, 5), (2, 512, 3, 3)]
    assert trunk.out_channels == 512


def test_spatial_softmax_keypoints_are_in_range_and_find_a_peak():
    torch.manual_seed(0)
    head = SpatialSoftmax(in_channels=4, num_keypoints=3)
    keypoints = head(100 * torch.randn(5, 4, 6, 7))
    assert keypoints.shape == (5, 3, 2)
    assert keypoints.abs().max() <= 1.0
    with torch.no_grad():
        head.project.weight.zero_()
        head.project.bias.zero_()
        head.project.weight[0, 0] = 1.0  # keypoint 0 follows channel 0
    features = torch.zeros(1, 4, 6, 7)
    features[0, 0, 0, 6] = 50.0  # top right
    x, y = head(features)[0, 0].tolist()
    assert x == pytest.approx(1.0, abs=1e-6) and y == pytest.approx(-1.0, abs=1e-6)
    assert head(torch.zeros(1, 4, 6, 7))[0].abs().max() < 1e-6  # uniform maps: the centre
    assert head(torch.randn(2, 4, 1, 1)).abs().max() == 0.0  # one position is the centre


def _coordinate_images(count: int, size: int) -> torch.Tensor:
    """(count, 1, size, size) images whose pixel value is row * size + column."""
    return torch.arange(size * size).reshape(1, 1, size, size).repeat(count, 1, 1, 1)


def test_random_crop_is_a_window_per_image_and_deterministic_under_seed():
    images = _coordinate_images(64, 84)
    crops = random_crop(images, 76, torch.Generator().manual_seed(3))
    assert crops.shape == (64, 1, 76, 76)
    tops, lefts = crops[:, 0, 0, 0] // 84, crops[:, 0, 0, 0] % 84
    for index in range(64):
        top, left = int(tops[index]), int(lefts[index])
        assert torch.equal(crops[index], images[index, :, top : top + 76, left : left + 76])
    assert 0 <= int(tops.min()) and int(tops.max()) <= 8 and len(set(tops.tolist())) > 3
    again = random_crop(images, 76, torch.Generator().manual_seed(3))
    assert torch.equal(crops, again)
    torch.manual_seed(7)
    first = random_crop(images, 76)
    torch.manual_seed(7)
    assert torch.equal(first, random_crop(images, 76))


def test_crop_module_is_random_in_training_and_centred_in_evaluation():
    images = _coordinate_images(16, 84)
    crop = ImageCrop(76)
    torch.manual_seed(0)
    assert not torch.equal(crop(images), crop(images))
    crop.eval()
    assert torch.equal(crop(images), crop(images))
    assert torch.equal(crop(images), center_crop(images, 76))
    assert int(crop(images)[0, 0, 0, 0]) == 4 * 84 + 4
    with pytest.raises(ValueError, match="crop size 90 does not fit images of 84 x 84 pixels"):
        center_crop(images, 90)


def _observations(config: ImageEncoderConfig, batch: tuple[int, ...], seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    images = {
        key: torch.randint(0, 256, (*batch, config.image_size, config.image_size, 3), generator=generator).to(
            torch.uint8
        )
        for key in config.image_keys
    }
    return images, torch.randn(*batch, 9, generator=generator)


def test_encoder_output_shape_and_train_eval_behaviour():
    config = ImageEncoderConfig(image_size=72, crop_size=64, base_channels=16, num_keypoints=4, feature_dim=8)
    torch.manual_seed(0)
    encoder = ImageEncoder(config, proprioception_dim=9)
    images, proprioception = _observations(config, (3, 2))
    features = encoder(images, proprioception)
    assert features.shape == (3, 2, 2 * 8 + 9) and encoder.output_dim == 25
    assert torch.equal(features[..., 16:], proprioception)  # proprioception passes through, after the cameras
    assert not torch.allclose(features, encoder(images, proprioception))  # new random crops move the keypoints
    encoder.eval()
    assert torch.equal(encoder(images, proprioception), encoder(images, proprioception))
    # Each observation is encoded on its own: the first step alone gives the same features.
    alone = encoder({key: value[:, :1] for key, value in images.items()}, proprioception[:, :1])
    torch.testing.assert_close(alone, encoder(images, proprioception)[:, :1])


def test_encoder_is_deterministic_under_seed():
    config = ImageEncoderConfig(image_size=72, crop_size=64, base_channels=16, num_keypoints=4, feature_dim=8)
    images, proprioception = _observations(config, (4,))
    outputs = []
    for _ in range(2):
        torch.manual_seed(11)
        encoder = ImageEncoder(config, proprioception_dim=9)
        outputs.append(encoder(images, proprioception))
    assert torch.equal(outputs[0], outputs[1])


def test_encoder_refuses_missing_cameras_and_wrong_images():
    config = ImageEncoderConfig(image_size=72, crop_size=64, base_channels=16, num_keypoints=4, feature_dim=8)
    encoder = ImageEncoder(config, proprioception_dim=9)
    images, proprioception = _observations(config, (2,))
    with pytest.raises(ValueError, match="missing camera key 'robot0_eye_in_hand_image'"):
        encoder({"agentview_image": images["agentview_image"]}, proprioception)
    with pytest.raises(ValueError, match=r"images\['agentview_image'\] shape \(2, 72, 72, 3\), dtype torch.float32"):
        encoder({**images, "agentview_image": images["agentview_image"].float()}, proprioception)
    with pytest.raises(ValueError, match=r"shape \(2, 64, 64, 3\), dtype torch.uint8: expected \(2, 72, 72, 3\)"):
        encoder({**images, "agentview_image": images["agentview_image"][:, :64, :64]}, proprioception)


def test_default_config_is_diffusion_policys_recipe_and_light_variant():
    config = ImageEncoderConfig()
    assert config.image_keys == ("agentview_image", "robot0_eye_in_hand_image")
    assert (config.image_size, config.crop_size, config.base_channels) == (84, 76, 64)
    assert (config.num_keypoints, config.feature_dim) == (32, 64)
    assert config.light().base_channels == 16 and config.light().cameras == config.cameras


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"cameras": ()}, "image_encoder.cameras=[]: must name at least one camera"),
        ({"cameras": ("agentview", "agentview")}, "image_encoder.cameras=['agentview', 'agentview']: names a camera"),
        ({"crop_size": 90}, "image_encoder.crop_size=90: must be an integer in [1, image_size=84]"),
        ({"base_channels": 24}, "image_encoder.base_channels=24: must be a positive multiple of 16"),
        ({"num_keypoints": 0}, "image_encoder.num_keypoints=0: must be an integer >= 1"),
        ({"feature_dim": 2.5}, "image_encoder.feature_dim=2.5: must be an integer >= 1"),
    ],
)
def test_config_refuses_bad_values_with_the_key(changes, message):
    with pytest.raises(ConfigError) as error:
        ImageEncoderConfig(**changes)
    assert str(error.value).startswith(message)
