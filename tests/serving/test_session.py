import numpy as np
import pytest

from carp.serving.session import RequestError, ServingSpec, Session
from tests.serving.conftest import SPEC


def obs(value: float) -> np.ndarray:
    return np.full(SPEC.obs_dim, value, np.float32)


def test_the_first_observation_fills_the_history_then_each_new_one_pushes_out_the_oldest():
    session = Session(SPEC)
    np.testing.assert_array_equal(session.observe({"obs": obs(1)}).obs_history, np.stack([obs(1), obs(1)]))
    np.testing.assert_array_equal(session.observe({"obs": obs(2)}).obs_history, np.stack([obs(1), obs(2)]))
    np.testing.assert_array_equal(session.observe({"obs": obs(3)}).obs_history, np.stack([obs(2), obs(3)]))
    restarted = session.observe({"obs": obs(4), "reset": True, "seed": 5})
    np.testing.assert_array_equal(restarted.obs_history, np.stack([obs(4), obs(4)]))
    assert restarted.echo == {"step": None, "timestamp": None}


@pytest.mark.parametrize(
    "request_, message",
    [
        ({}, "obs: missing"),
        ({"obs": [1.0, 2.0, 3.0]}, "obs: expected a float32 array"),
        ({"obs": np.zeros(4, np.float32)}, r"obs: expected shape \(3,\), got \(4,\)"),
        ({"obs": np.zeros(3)}, "obs: expected dtype float32, got float64"),
        ({"obs": np.array([0, np.nan, 0], np.float32)}, "obs: holds NaN"),
        ({"obs": np.zeros(3, np.float32), "reset": 1}, "reset: expected true or false"),
        ({"obs": np.zeros(3, np.float32), "predict": "no"}, "predict: expected true or false"),
        ({"obs": np.zeros(3, np.float32), "seed": "3"}, "seed: expected an integer"),
        ({"obs": np.zeros(3, np.float32), "step": 1.5}, "step: expected an integer"),
        ({"obs": np.zeros(3, np.float32), "timestamp": "now"}, "timestamp: expected a number"),
        ([1, 2], "request: expected a map"),
    ],
)
def test_a_bad_request_names_its_key_and_leaves_the_history_unchanged(request_, message):
    session = Session(SPEC)
    session.observe({"obs": obs(1)})
    with pytest.raises(RequestError, match=message):
        session.observe(request_)
    np.testing.assert_array_equal(session.observe({"obs": obs(2)}).obs_history, np.stack([obs(1), obs(2)]))


def test_an_image_policy_needs_uint8_images_of_the_declared_shape():
    spec = ServingSpec(("state",), 2, 3, 8, 2, 4, 0.05, image_shape=(2, 3, 4, 4))
    session = Session(spec)
    with pytest.raises(RequestError, match="images: missing"):
        session.observe({"obs": obs(1)})
    with pytest.raises(RequestError, match="images: expected dtype uint8"):
        session.observe({"obs": obs(1), "images": np.zeros((2, 3, 4, 4), np.float32)})
    observed = session.observe({"obs": obs(1), "images": np.ones((2, 3, 4, 4), np.uint8)})
    assert observed.image_history.shape == (2, 2, 3, 4, 4)
    assert spec.observation_spec()["images"] == {"shape": [2, 3, 4, 4], "dtype": "uint8", "layout": "cameras, 3, h, w"}


def test_the_spec_refuses_an_executed_slice_beyond_the_chunk():
    with pytest.raises(ValueError, match=r"To - 1 \+ Ta = 9 exceeds H = 8"):
        ServingSpec(("state",), 2, 3, 8, 2, 8, 0.05)


def per_key(value: float) -> dict[str, np.ndarray]:
    """The request form that sends each key of the spec by its name: object (1,), robot0_eef_pos (2,)."""
    return {"object": np.full(1, value, np.float32), "robot0_eef_pos": np.full(2, value, np.float32)}


def test_per_key_observations_are_concatenated_in_the_specs_order():
    session = Session(SPEC)
    keys = {"object": np.array([1], np.float32), "robot0_eef_pos": np.array([2, 3], np.float32)}
    np.testing.assert_array_equal(session.observe(keys).obs_history, np.array([[1, 2, 3], [1, 2, 3]], np.float32))
    # Mixed forms across requests share one history.
    np.testing.assert_array_equal(session.observe({"obs": obs(4)}).obs_history[0], [1, 2, 3])
    assert SPEC.key_spec() == {
        "object": {"shape": [1], "dtype": "float32"},
        "robot0_eef_pos": {"shape": [2], "dtype": "float32"},
    }


@pytest.mark.parametrize(
    "request_, message",
    [
        ({"object": np.zeros(1, np.float32)}, "robot0_eef_pos: missing"),
        (per_key(0) | {"object": np.zeros(2, np.float32)}, r"object: expected shape \(1,\), got \(2,\)"),
        (per_key(0) | {"robot0_eef_pos": np.zeros(2)}, "robot0_eef_pos: expected dtype float32, got float64"),
        (per_key(0) | {"obs": obs(0)}, "object: send either obs or the per-key observations, not both"),
        ({"step": 3}, r"obs: missing \(send obs \(3,\) float32 or each of object, robot0_eef_pos\)"),
    ],
)
def test_a_bad_per_key_request_names_its_key(request_, message):
    session = Session(SPEC)
    with pytest.raises(RequestError, match=message):
        session.observe(request_)


def test_without_known_widths_only_the_concatenated_obs_is_accepted():
    spec = ServingSpec(("object", "robot0_eef_pos"), 2, 3, 8, 2, 4, 0.05)
    assert spec.key_spec() == {}
    with pytest.raises(RequestError, match=r"obs: missing \(send obs \(3,\) float32\)$"):
        Session(spec).observe(per_key(0))


def test_the_spec_refuses_widths_that_do_not_add_up_to_do():
    with pytest.raises(ValueError, match=r"obs_widths \[1, 1\] of keys \['object', 'robot0_eef_pos'\] do not add up"):
        ServingSpec(("object", "robot0_eef_pos"), 2, 3, 8, 2, 4, 0.05, obs_widths=(1, 1))
