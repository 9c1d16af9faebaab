import io
import pickle

import numpy as np
import pytest
import torch
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.diagrams import (CheckpointError, load_checkpoint, load_taxinet,
                                 save_checkpoint)
from reachwatch.systems import (PreprocessConfig, ProportionalController, TaxiNet,
                                TaxiNetConfig, build_taxinet, preprocess)


def _model(seed=0, config=None):
    torch.manual_seed(seed)
    return build_taxinet(config or TaxiNetConfig(), PreprocessConfig())


def _image(h=200, w=360, seed=0):
    rng = np.random.default_rng(seed)
    image = ImageRgba8U(w, h)
    image.mutable_data[:] = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
    return image


@pytest.mark.parametrize("estimate, expected_deg", [
    ([0.0, 0.0], 0.0), ([1.0, 0.0], -0.74), ([0.0, 1.0], -0.44), ([-2.0, 10.0], 1.48 - 4.4)])
def test_p_controller_formula(estimate, expected_deg):
    p = ProportionalController()
    context = p.CreateDefaultContext()
    p.get_estimate_input_port().FixValue(context, estimate)
    phi = p.get_steering_angle_output_port().Eval(context)[0]
    assert phi == pytest.approx(np.deg2rad(expected_deg))


def test_left_of_centreline_steers_back_right():
    # px > 0 is left; a negative steering angle turns theta negative, towards -px.
    p = ProportionalController()
    context = p.CreateDefaultContext()
    p.get_estimate_input_port().FixValue(context, [4.0, 0.0])
    assert p.get_steering_angle_output_port().Eval(context)[0] < 0
    p.get_estimate_input_port().FixValue(context, [-4.0, 0.0])
    assert p.get_steering_angle_output_port().Eval(context)[0] > 0


def test_p_controller_saturation_option():
    p = ProportionalController(max_steering_deg=10.0)
    assert p.steering_deg([100.0, 0.0]) == pytest.approx(-10.0)


def test_blockmax_preprocessing_shape_and_range():
    images = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (5, 200, 360, 3),
                                                                 dtype=np.uint8))
    x = preprocess(images, PreprocessConfig())
    assert x.shape == (5, 128)
    assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    with pytest.raises(ValueError, match="RGB"):
        preprocess(images[..., :2], PreprocessConfig())
    # A camera frame's alpha channel is ignored: RGBA in, the same input out.
    rgba = torch.cat([images, torch.full((5, 200, 360, 1), 7, dtype=torch.uint8)], dim=-1)
    for config in (PreprocessConfig(), PreprocessConfig(kind="resize", height=32, width=64)):
        torch.testing.assert_close(preprocess(rgba, config), preprocess(images, config),
                                   rtol=0, atol=0)


def test_taxinet_system_output_shape_and_determinism():
    system = TaxiNet(model=_model(), preprocess_config=PreprocessConfig(),
                     image_size=(200, 360))
    context = system.CreateDefaultContext()
    system.get_color_image_input_port().FixValue(context, _image())
    a = system.get_estimate_output_port().Eval(context).copy()
    b = TaxiNet(model=_model(), preprocess_config=PreprocessConfig()).estimate(
        _image().data[None, ..., :3])[0]
    assert a.shape == (2,)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    system.get_color_image_input_port().FixValue(context, _image(seed=1))
    assert not np.allclose(system.get_estimate_output_port().Eval(context), a)


def test_taxinet_rejects_wrong_image_size():
    system = TaxiNet(model=_model(), preprocess_config=PreprocessConfig(),
                     image_size=(200, 360))
    context = system.CreateDefaultContext()
    system.get_color_image_input_port().FixValue(context, _image(64, 128))
    with pytest.raises(ValueError, match="64x128.*200x360"):
        system.get_estimate_output_port().Eval(context)


def _save(path, model, config=None):
    return save_checkpoint(path, kind="taxinet", model=model,
                           model_config=config or TaxiNetConfig(),
                           preprocess_config=PreprocessConfig(),
                           metadata={"image_size": [200, 360], "loss": np.float64(0.5),
                                     "torch": torch.__version__})


def test_checkpoint_round_trip(tmp_path):
    model = _model(3)
    path = _save(tmp_path / "a.pt", model)
    loaded, preprocess_config, metadata = load_taxinet(path)
    x = torch.rand(4, 128)
    torch.testing.assert_close(loaded(x), model(x))
    assert metadata["image_size"] == [200, 360] and metadata["loss"] == 0.5
    assert preprocess_config == PreprocessConfig()
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


def test_bad_checkpoints_fail_clearly(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_taxinet(tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match=r"^\S+ is a folder, not a checkpoint file$"):
        load_taxinet(tmp_path)
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"empty.pt is empty, not a checkpoint$"):
        load_taxinet(tmp_path / "empty.pt")
    (tmp_path / "pickled.pt").write_bytes(pickle.dumps(object(), protocol=2))
    with pytest.raises(CheckpointError, match=r"pickled.pt is not a readable checkpoint .*: "
                                              r"not a torch.save archive$"):
        load_taxinet(tmp_path / "pickled.pt")
    pickled = io.BytesIO()                       # an archive holding a pickled object
    torch.save({"model": object()}, pickled)
    (tmp_path / "objects.pt").write_bytes(pickled.getvalue())
    with pytest.raises(CheckpointError, match=r"objects.pt is not a readable checkpoint .*: "
                                              r"UnpicklingError: it holds Python objects that "
                                              r"a weights-only load refuses$"):
        load_taxinet(tmp_path / "objects.pt")
    good = _save(tmp_path / "good.pt", _model()).read_bytes()
    (tmp_path / "truncated.pt").write_bytes(good[: len(good) // 2])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_taxinet(tmp_path / "truncated.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="not a readable checkpoint .*: not a torch.save "
                                              "archive$"):
        load_taxinet(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not a reachwatch checkpoint"):
        load_taxinet(tmp_path / "foreign.pt")
    save_checkpoint(tmp_path / "det.pt", kind="detector", model=_model(),
                    model_config=TaxiNetConfig(), preprocess_config=PreprocessConfig(),
                    metadata={})
    with pytest.raises(CheckpointError, match="'detector' model"):
        load_taxinet(tmp_path / "det.pt")
    # weights of a wider net under the default config's name
    payload = load_checkpoint(_save(tmp_path / "wide.pt", _model(config=TaxiNetConfig(
        hidden=[32, 8, 8]))), kind="taxinet")
    payload["model_config"]["hidden"] = [16, 8, 8]
    torch.save(payload, tmp_path / "mismatch.pt")
    with pytest.raises(CheckpointError, match="do not fit"):
        load_taxinet(tmp_path / "mismatch.pt")
