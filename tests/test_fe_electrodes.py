"""Physics of the fluid-film electrode model: rest, locality, monotonicity, symmetry, clipping, noise."""

import subprocess
import sys

import numpy as np
import pytest

from assets.biotac import BioTacGeometry, make_biotac, vertex_normals
from fe.electrodes import ADC_MAX, N_ELECTRODES, ElectrodeModel, ElectrodeParameters
from learn.synthetic import gaussian_dent


@pytest.fixture(scope="module")
def geometry() -> BioTacGeometry:
    return make_biotac(max_edge=1e-3)


@pytest.fixture(scope="module")
def model(geometry: BioTacGeometry) -> ElectrodeModel:
    return ElectrodeModel(geometry, ElectrodeParameters())


def skin_point_over(geometry: BioTacGeometry, electrode: int, lateral: np.ndarray | None = None) -> np.ndarray:
    """The skin vertex nearest the ray from electrode `electrode` (0-based) along its normal, shifted."""
    e = geometry.electrodes
    target = e.positions[electrode] + 1.5e-3 * e.normals[electrode]
    if lateral is not None:
        target = target + lateral
    v = geometry.skin.vertices
    return v[np.argmin(np.linalg.norm(v - target, axis=1))]


def mirror_permutation(geometry: BioTacGeometry) -> np.ndarray:
    """perm[e] = the electrode at the y-mirrored position of electrode e."""
    p = geometry.electrodes.positions
    mirrored = p * [1.0, -1.0, 1.0]
    dist = np.linalg.norm(mirrored[:, None, :] - p[None, :, :], axis=2)
    assert np.all(dist.min(axis=1) < 1e-9)
    return dist.argmin(axis=1)


def test_counts_equal_offset_at_the_reference_skin(geometry: BioTacGeometry) -> None:
    params = ElectrodeParameters.sample(np.random.default_rng(0))
    model = ElectrodeModel(geometry, params)
    np.testing.assert_allclose(model.counts(geometry.skin.vertices), params.offset, atol=1e-9)


@pytest.mark.parametrize("electrode", [0, 3, 9, 16, 17])
def test_dent_over_an_electrode_lowers_it_most_and_monotonically(
    geometry: BioTacGeometry, model: ElectrodeModel, electrode: int
) -> None:
    point = skin_point_over(geometry, electrode)
    rest = model.counts(geometry.skin.vertices)
    drops = np.array(
        [
            rest - model.counts(gaussian_dent(geometry, geometry.skin.vertices, point, d))
            for d in (0.3e-3, 0.6e-3, 0.9e-3)
        ]
    )
    assert np.all(np.diff(drops[:, electrode]) > 0.0), "deeper dent, lower count"
    # far from the dent only tilted vertex normals shift the sampled inner surface: < 1 count either way
    assert np.all(drops >= -1.0), "an inward dent never raises a count"
    assert np.argmax(drops[-1]) == electrode
    far = np.linalg.norm(geometry.electrodes.positions - geometry.electrodes.positions[electrode], axis=1) > 8e-3
    assert drops[-1, far].max() < 0.05 * drops[-1, electrode]


def test_nearer_dent_lowers_an_electrode_more(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    """Sliding the same dent away from E17 along x steadily weakens E17's response."""
    rest = model.counts(geometry.skin.vertices)[16]
    drops = []
    for dx in (0.0, 1.5e-3, 3.0e-3, 4.5e-3):
        point = skin_point_over(geometry, 16, lateral=np.array([dx, 0.0, 0.0]))
        drops.append(rest - model.counts(gaussian_dent(geometry, geometry.skin.vertices, point, 0.6e-3))[16])
    assert np.all(np.diff(drops) < 0.0)


def test_skin_moving_away_raises_counts(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    v = geometry.skin.vertices
    inflated = v + 0.3e-3 * vertex_normals(v, geometry.skin.triangles) * ~geometry.skin.anchored[:, None]
    assert np.all(model.counts(inflated) > model.counts(v))


def test_mirror_symmetry(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    perm = mirror_permutation(geometry)
    assert sorted(perm.tolist()) == list(range(N_ELECTRODES)) and perm[0] == 10 and perm[7] == 8
    rest = model.counts(geometry.skin.vertices)
    np.testing.assert_allclose(rest, rest[perm])
    point = skin_point_over(geometry, 2, lateral=np.array([1e-3, 0.0, 0.0]))
    mirrored_point = point * [1.0, -1.0, 1.0]
    a = rest - model.counts(gaussian_dent(geometry, geometry.skin.vertices, point, 0.6e-3))
    b = rest - model.counts(gaussian_dent(geometry, geometry.skin.vertices, mirrored_point, 0.6e-3))
    assert a[2] > 50.0
    # the mesh is mirror-symmetric up to its meshing (<= 0.4 mm vertex offsets on the tip cap)
    np.testing.assert_allclose(b, a[perm], atol=0.03 * a.max())


def test_clipping_to_12_bits(geometry: BioTacGeometry) -> None:
    v = geometry.skin.vertices
    loud = ElectrodeParameters(offset=np.full(N_ELECTRODES, 4050.0), gain=np.full(N_ELECTRODES, 3.0))
    model = ElectrodeModel(geometry, loud)
    away = v + 1e-3 * vertex_normals(v, geometry.skin.triangles) * ~geometry.skin.anchored[:, None]
    assert np.all(model.counts(away) == ADC_MAX)
    crushed = gaussian_dent(geometry, v, skin_point_over(geometry, 16), 3e-3, width=4e-3)
    quiet = ElectrodeModel(geometry, ElectrodeParameters(offset=np.full(N_ELECTRODES, 300.0)))
    assert quiet.counts(crushed)[16] == 0.0
    assert model.pdc_counts(-1e3) == 0.0 and model.pdc_counts(1e6) == ADC_MAX


def test_pdc_is_monotone_and_spans_100_kpa(model: ElectrodeModel) -> None:
    pressures = np.linspace(0.0, 99e3, 12)
    pdc = np.array([model.pdc_counts(p) for p in pressures])
    assert np.all(np.diff(pdc) > 0.0)
    assert pdc[0] == pytest.approx(0.0) and model.pdc_counts(100e3) == pytest.approx(ADC_MAX)


def test_noise_statistics_and_quantisation(geometry: BioTacGeometry) -> None:
    params = ElectrodeParameters(noise_std=4.0, pdc_noise_std=2.0)
    model = ElectrodeModel(geometry, params)
    rng = np.random.default_rng(1)
    draws = np.array([model.counts(geometry.skin.vertices, rng=rng) for _ in range(400)])
    assert np.all(draws == np.rint(draws))
    assert np.abs(draws.mean(axis=0) - params.offset).max() < 5 * 4.0 / np.sqrt(400)
    std = draws.std(axis=0)
    assert 3.5 < std.mean() < 4.5  # sqrt(16 + 1/12) with rounding
    assert np.abs(np.corrcoef(draws.T)[np.triu_indices(N_ELECTRODES, 1)]).max() < 0.25
    pdc = np.array([model.pdc_counts(20e3, rng=rng) for _ in range(400)])
    assert abs(pdc.mean() - model.pdc_counts(20e3)) < 0.5 and 1.6 < pdc.std() < 2.4
    again = ElectrodeModel(geometry, params).counts(geometry.skin.vertices, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(again, draws[0])


def test_drift_warms_up_to_its_amplitude(geometry: BioTacGeometry) -> None:
    amplitude = np.linspace(-40.0, 40.0, N_ELECTRODES)
    model = ElectrodeModel(geometry, ElectrodeParameters(drift_amplitude=amplitude, drift_time_constant=100.0))
    v = geometry.skin.vertices
    at = [model.counts(v, time_s=t) - model.params.offset for t in (0.0, 50.0, 100.0, 2000.0)]
    np.testing.assert_allclose(at[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(at[2], amplitude * (1 - np.exp(-1.0)), atol=1e-9)
    np.testing.assert_allclose(at[3], amplitude, atol=1e-6)
    with pytest.raises(ValueError):
        model.counts(v, time_s=-1.0)


def test_sampled_sensors_are_plausible_and_reproducible() -> None:
    a = ElectrodeParameters.sample(np.random.default_rng(3))
    b = ElectrodeParameters.sample(np.random.default_rng(3))
    c = ElectrodeParameters.sample(np.random.default_rng(4))
    np.testing.assert_array_equal(a.offset, b.offset)
    assert np.abs(a.offset - c.offset).max() > 100.0
    assert np.all((a.offset >= 2100) & (a.offset <= 3700))
    assert set(a.to_dict()) >= {"offset", "gain", "pdc_gain"}


def test_bad_inputs_are_rejected(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    with pytest.raises(ValueError, match="19"):
        ElectrodeParameters(offset=np.zeros(18))
    with pytest.raises(ValueError, match="gain"):
        ElectrodeParameters(gain=np.zeros(N_ELECTRODES))
    with pytest.raises(ValueError, match="shape"):
        model.counts(geometry.skin.vertices[:-1])
    with pytest.raises(ValueError, match="skin_thickness"):
        ElectrodeModel(geometry, skin_thickness=1.57)  # millimetres by mistake
    with pytest.raises(ValueError, match="pressure"):
        model.pdc_counts(float("nan"))


def test_import_is_cheap_and_torch_free() -> None:
    code = "import sys, learn, fe.electrodes, learn.synthetic; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_vectorised_impedance_matches_a_direct_evaluation(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    """The film impedance written out electrode by electrode from its definition (all vertex normals)."""
    v = gaussian_dent(geometry, geometry.skin.vertices, skin_point_over(geometry, 12), 0.8e-3, shear=[3e-4, 0, 0])
    inner = v - 0.5 * model.skin_thickness * vertex_normals(v, geometry.skin.triangles)
    p = geometry.skin.vertices[geometry.skin.triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    vertex_area = np.zeros(len(v))
    np.add.at(vertex_area, geometry.skin.triangles.ravel(), np.repeat(area / 3.0, 3))
    radius, floor = model.params.footprint_radius, model.params.min_gap
    expected = []
    for pos, n in zip(geometry.electrodes.positions, geometry.electrodes.normals, strict=True):
        rel = inner - pos
        along = rel @ n
        lateral = np.linalg.norm(rel - along[:, None] * n, axis=1)
        in_front = (geometry.skin.vertices - pos) @ n > 0.0  # the skin on the electrode's side
        w = vertex_area * np.clip(1.0 - (lateral / radius) ** 2, 0.0, None) ** 2 * in_front
        expected.append((w / np.maximum(along, floor)).sum() / w.sum())
    np.testing.assert_allclose(model.impedance(v), expected, rtol=1e-9)


def test_many_skins_at_once_equal_one_at_a_time(geometry: BioTacGeometry, model: ElectrodeModel) -> None:
    """`impedances` (chunked, vectorised over skins) gives each skin exactly what `impedance` gives it alone,
    chunk boundaries included; a non-finite skin anywhere is refused."""
    skins = np.array(
        [
            gaussian_dent(geometry, geometry.skin.vertices, skin_point_over(geometry, e), depth, shear=[2e-4, 0, 0])
            for e in range(N_ELECTRODES)
            for depth in (0.3e-3, 0.9e-3)
        ]
    )
    chunk = model.CHUNK_TRIANGLES // len(model._near_triangles)
    assert 1 <= chunk < len(skins)  # more than one chunk
    many = model.impedances(skins)
    assert many.shape == (len(skins), N_ELECTRODES)
    np.testing.assert_array_equal(many, [model.impedance(v) for v in skins])
    np.testing.assert_array_equal(
        model.relative_impedances(skins[:2]), [model.relative_impedance(v) for v in skins[:2]]
    )
    skins[-1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        model.impedances(skins)
