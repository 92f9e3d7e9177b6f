"""The learned forward model (FE field -> a particular sensor's electrodes) fits a sensor it was not told about."""

from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from fe.electrodes import ElectrodeModel, ElectrodeParameters
from learn.forward import ForwardModel, campaign_field_samples, fit_and_score, physics_features
from learn.synthetic import write_synthetic_campaign

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # a sensor far from nominal: gains 0.6-1.6, load ratios 0.5-2, offsets spread; the model must find them
    rng = np.random.default_rng(21)
    params = ElectrodeParameters(
        offset=rng.uniform(2100, 3700, 19),
        gain=rng.uniform(0.6, 1.6, 19),
        load_ratio=rng.uniform(0.5, 2.0, 19),
        noise_std=3.0,
    )
    return write_synthetic_campaign(tmp_path_factory.mktemp("fwd") / "biotac3.hdf5", 30, 3, seed=21, params=params)


def test_forward_model_fits_a_sensor(campaign: Path, tmp_path: Path) -> None:
    samples = campaign_field_samples(campaign, skin_thickness=1.58e-3)
    model, scores = fit_and_score(samples, test_fraction=0.25, seed=0)
    assert scores["rmse_counts"] < 0.25 * scores["mean_predictor_rmse_counts"]
    nominal = ForwardModel(max_epochs=0).fit(samples)  # the physics read-out with gain 1, load ratio 1
    rows = np.arange(len(samples.features))
    nominal_rmse = np.sqrt(np.mean((nominal.predict(samples.features[rows]) - samples.electrodes[rows]) ** 2))
    assert scores["rmse_counts"] < 0.5 * nominal_rmse
    path = model.save(tmp_path / "forward.pt", {"note": "test"})
    loaded, record = ForwardModel.load(path)
    np.testing.assert_allclose(loaded.predict(samples.features[:5]), model.predict(samples.features[:5]), rtol=1e-6)
    assert record == {"note": "test"}


def test_counts_from_a_deformed_mesh(campaign: Path) -> None:
    with h5py.File(campaign, "r") as f:
        reference, triangles = f["mesh/vertices"][:], f["mesh/triangles"][:]
        displacement = f["nodal_res/data"][7]
    physics = ElectrodeModel.from_mesh(reference, triangles, skin_thickness=1.58e-3)
    samples = campaign_field_samples(campaign, skin_thickness=1.58e-3)
    np.testing.assert_allclose(physics_features(physics, reference + displacement), samples.features[7])
    model = ForwardModel(max_epochs=0).fit(samples)
    np.testing.assert_allclose(model.counts(physics, reference), 0.0, atol=1e-3)  # rest reads zero when tared
    with pytest.raises(ValueError, match="nodal_res"):
        bare = campaign.with_name("bare.hdf5")
        with h5py.File(bare, "w") as f:
            f["electrode_vals/data"] = np.zeros((2, 19))
        campaign_field_samples(bare)
