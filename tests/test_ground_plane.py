"""Ground plane per frame: the general GAC offset / disparity prior (level plane = the paper's
formulas, tilted planes = an independent ray-plane computation), the module with a plane input,
``planes/`` files, and the plane carried by sources and transforms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data import transforms
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti import format_plane, parse_plane, read_plane, write_plane
from gac_jax.data.sources import KittiObjectSource
from gac_jax.models.ground_aware_conv import (
    GroundAwareConv,
    base_offset,
    bilinear_gather,
    disparity_prior,
    feature_projection,
    vertical_gather,
)
from gac_jax.models.ground_plane import ground_maps
from tests.tilted_frames import write_tilted_root

KITTI_P2 = np.array(
    [
        [7.215377e02, 0.0, 6.095593e02, 4.485728e01],
        [0.0, 7.215377e02, 1.728540e02, 2.163791e-01],
        [0.0, 0.0, 1.0, 2.745884e-03],
    ]
)


def tilted(pitch_deg: float, roll_deg: float = 0.0, height: float = 1.65) -> np.ndarray:
    """Plane of a camera pitched down by ``pitch_deg`` and rolled by ``roll_deg``."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    return np.array([np.sin(r), -np.cos(r) * np.cos(p), -np.cos(r) * np.sin(p), height])


def maps64(P, plane, size, stride=1.0, h=1.535, baseline=0.54, formula="paper"):
    """(offset rows, offset cols, disparity) (H, W) float64 of one frame."""
    with jax.enable_x64(True):
        Pf = feature_projection(jnp.asarray(P, jnp.float64)[None], stride)
        out = ground_maps(Pf, jnp.asarray(plane, jnp.float64)[None], size, h, baseline, formula)
        return tuple(np.asarray(x[0]) for x in out)


# ---------------------------------------------------------------------------------------------
# the general forms


def test_level_plane_gives_the_paper_formulas_by_hand():
    """fy = 700, cy = 100, Ty = 0.2, h = 1.5, EL = 1.65: offset h (v - cy) / (2 EL - h),
    disparity fy B (v - cy) / (fy EL + Ty), 0 at and above the horizon; every column alike."""
    P = np.array([[700.0, 0, 300, 40.0], [0, 700.0, 100, 0.2], [0, 0, 1, 0.003]])
    offset, cols, disp = maps64(P, geometry.level_plane(1.65), (201, 7), h=1.5)
    assert not cols.any()  # a level plane: the bottom point is straight below
    assert offset[150, 3] == pytest.approx(41.666666666666664, rel=1e-12)  # 1.5 * 50 / 1.8
    assert disp[150, 3] == pytest.approx(700 * 0.54 * 50 / 1155.2, rel=1e-12)  # 16.3608...
    assert disp[150, 3] == pytest.approx(16.360803324099724, rel=1e-12)
    assert offset[100].max() == disp[100].max() == 0.0
    assert offset[:100].max() == disp[:100].max() == 0.0
    np.testing.assert_array_equal(offset, offset[:, :1].repeat(7, axis=1))
    v1, _, _ = maps64(P, geometry.level_plane(1.65), (201, 7), h=1.5, formula="reference_v1")
    assert v1[150, 0] == pytest.approx(1.5 * 50 / 2 * (1.65 - 0.75), rel=1e-12)  # 33.75


@pytest.mark.parametrize("formula", ["paper", "reference", "reference_v1"])
@pytest.mark.parametrize("stride", [16, 8])
def test_level_plane_equals_base_offset_and_disparity_prior(formula, stride):
    """On the real KITTI P2, every row and column, float64."""
    H, W = 375 // stride, 1242 // stride
    level = geometry.level_plane(1.65)
    offset, cols, disp = maps64(KITTI_P2, level, (H, W), stride, formula=formula)
    assert not cols.any()
    with jax.enable_x64(True):
        P = jnp.asarray(KITTI_P2[None], jnp.float64)
        ref_offset = np.asarray(base_offset(H, P, stride, offset_formula=formula))[0]
        ref_disp = np.asarray(disparity_prior(H, P, stride))[0]
    assert ref_offset.max() > 1.0 and ref_disp.max() > 1.0
    np.testing.assert_allclose(offset, ref_offset[:, None].repeat(W, 1), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(disp, ref_disp[:, None].repeat(W, 1), rtol=1e-12, atol=1e-12)


def ray_plane_offset(P, plane, u, v, h):
    """(rows, cols) from the centre seen at (u, v) to its bottom point (rays from the origin)."""
    M, n, d = P[:, :3], plane[:3], plane[3]
    r = np.linalg.solve(M, [u, v, 1.0])
    t = (h / 2 - d) / (n @ r)  # n . (t r) + d = h / 2
    if t <= 0:
        return 0.0, 0.0
    bottom = t * r - h / 2 * n
    assert geometry.height_above_plane(bottom, plane) == pytest.approx(0.0, abs=1e-9)
    p = M @ bottom
    return max(p[1] / p[2] - v, 0.0), p[0] / p[2] - u


def ray_plane_disparity(P, plane, u, v, baseline):
    """fy B / z of the road point seen at (u, v), rays from -M^-1 [Tx, Ty, 0] (Tz dropped)."""
    M, n, d = P[:, :3], plane[:3], plane[3]
    C = -np.linalg.solve(M, [P[0, 3], P[1, 3], 0.0])
    r = np.linalg.solve(M, [u, v, 1.0])
    t = -(n @ C + d) / (n @ r)
    if t <= 0:
        return 0.0
    return max(P[1, 1] * baseline / (C + t * r)[2], 0.0)


@pytest.mark.parametrize(
    "plane", [tilted(20.0), tilted(-4.0, 3.0, 1.2), tilted(8.0, -10.0, 2.4)], ids=str
)
def test_tilted_planes_equal_a_ray_plane_intersection(plane):
    stride, (H, W), h = 16.0, (24, 78), 1.535
    Pf = KITTI_P2 * np.array([[1 / stride], [1 / stride], [1.0]])
    offset, cols, disp = maps64(KITTI_P2, plane, (H, W), stride, h=h)
    rng = np.random.default_rng(0)
    for v, u in zip(rng.integers(0, H, 40), rng.integers(0, W, 40), strict=True):
        rows_want, cols_want = ray_plane_offset(Pf, plane, u, v, h)
        assert offset[v, u] == pytest.approx(rows_want, abs=1e-9)
        assert cols[v, u] == pytest.approx(cols_want, abs=1e-9)
        assert disp[v, u] == pytest.approx(ray_plane_disparity(Pf, plane, u, v, 0.54), abs=1e-9)
    assert offset.max() > 1.0 and disp.max() > 1.0 and np.abs(cols).max() > 0.1
    assert np.ptp(offset[H // 2]) > 1e-3 or plane[0] == 0  # a roll varies along the row


# ---------------------------------------------------------------------------------------------
# the module


@pytest.fixture(scope="module")
def gac():
    module = GroundAwareConv(stride=16)
    x = jax.random.uniform(jax.random.key(0), (2, 12, 40, 8))
    P = jnp.asarray(np.stack([KITTI_P2, KITTI_P2 * [[1.1], [1.1], [1.0]]]), jnp.float32)
    variables = module.init(jax.random.key(1), x, P)
    variables = jax.tree.map(lambda a: a + 0.5, variables)  # alpha != 0
    return module, variables, x, P


def test_module_default_plane_is_the_level_plane_of_its_camera_height(gac):
    module, variables, x, P = gac
    default = module.apply(variables, x, P)
    level = np.tile(np.float32(geometry.level_plane(module.camera_height)), (2, 1))
    explicit = module.apply(variables, x, P, jnp.asarray(level))
    for key in default:
        np.testing.assert_array_equal(np.asarray(default[key]), np.asarray(explicit[key]))


def test_module_takes_the_plane_as_an_input_without_retracing(gac):
    module, variables, x, P = gac
    apply = jax.jit(module.apply)
    level = np.tile(np.float32(geometry.level_plane(1.65)), (2, 1))
    pitched = np.float32([tilted(20.0), tilted(5.0, 4.0, 1.4)])
    a, b = apply(variables, x, P, level), apply(variables, x, P, pitched)
    assert apply._cache_size() == 1
    assert np.abs(np.asarray(a["offset_rows"]) - np.asarray(b["offset_rows"])).max() > 0.1
    assert not np.asarray(a["offset_cols"]).any() and np.abs(b["offset_cols"]).max() > 0.1
    assert np.abs(np.asarray(a["features"]) - np.asarray(b["features"])).max() > 1e-3
    with pytest.raises(ValueError, match="plane must have shape"):
        module.apply(variables, x, P, level[:1])


def test_bilinear_gather_is_vertical_gather_at_integer_columns_and_else_bilinear():
    rng = np.random.default_rng(0)
    f = jnp.asarray(rng.normal(size=(2, 5, 6, 3)), jnp.float32)
    rows = jnp.asarray(rng.uniform(-1, 6, (2, 5, 6)), jnp.float32)
    u = jnp.broadcast_to(jnp.arange(6.0), (2, 5, 6))
    np.testing.assert_array_equal(bilinear_gather(f, rows, u), vertical_gather(f, rows))
    cols = jnp.asarray(rng.uniform(-1, 7, (2, 5, 6)), jnp.float32)
    got = np.asarray(bilinear_gather(f, rows, cols))
    fn = np.asarray(f, np.float64)
    for b, v, c in [(0, 1, 2), (1, 4, 5), (1, 0, 0), (0, 3, 4)]:
        r, q = np.clip(float(rows[b, v, c]), 0, 4), np.clip(float(cols[b, v, c]), 0, 5)
        r0, q0 = min(int(r), 3), min(int(q), 4)
        wr, wq = r - r0, q - q0
        want = (1 - wr) * (1 - wq) * fn[b, r0, q0] + wr * (1 - wq) * fn[b, r0 + 1, q0]
        want += (1 - wr) * wq * fn[b, r0, q0 + 1] + wr * wq * fn[b, r0 + 1, q0 + 1]
        np.testing.assert_allclose(got[b, v, c], want, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# planes/ files

AVOD_000000 = "# Plane\nWidth 4\nHeight 1\n-7.051729e-03 -9.997791e-01 -1.980151e-02 1.680367e+00\n"


def test_planes_file_is_read_normalised_and_round_trips(tmp_path):
    plane = parse_plane(AVOD_000000)
    assert np.linalg.norm(plane[:3]) == pytest.approx(1.0, abs=1e-15)
    assert plane[1] < 0 and plane[3] == pytest.approx(1.680367, rel=1e-6)
    # any scale and sign of the same plane, without the header, reads the same
    np.testing.assert_allclose(parse_plane("0.014103458 1.9995582 0.03960302 -3.360734"), plane)
    write_plane(tmp_path / "planes" / "000007.txt", plane)
    np.testing.assert_allclose(read_plane(tmp_path / "planes" / "000007.txt"), plane, rtol=1e-12)
    assert format_plane(plane).startswith("# Plane\nWidth 4\nHeight 1\n")


@pytest.mark.parametrize(
    "text, problem",
    [
        ("", "found 0"),
        ("Width 3\nHeight 1\n0 -1 0 1.65\n", "expected 'Width 4'"),
        ("0 -1 0\n", "expected 4 numbers"),
        ("0 -1 zero 1.65\n", "expected 4 numbers"),
        ("0 -1 0 1.65\n0 -1 0 1.6\n", "found 2"),
        ("1 0 0 1.65\n", "not a ground plane"),
        ("0 -1 0 nan\n", "not a ground plane"),
        ("0 -1 0 -1.65\n", "not above the plane"),
    ],
)
def test_malformed_planes_files_name_the_file(tmp_path, text, problem):
    path = tmp_path / "000001.txt"
    path.write_text(text)
    with pytest.raises(KittiFormatError, match=problem) as err:
        read_plane(path)
    assert str(path) in str(err.value)


# ---------------------------------------------------------------------------------------------
# sources and transforms


@pytest.fixture(scope="module")
def tilted_root(tmp_path_factory):
    return write_tilted_root(tmp_path_factory.mktemp("tilted"), 2)


def road_points(sample) -> tuple[np.ndarray, np.ndarray]:
    """The labels' bottom centres (on the road) and their pixels through the sample's P2."""
    objects = sample["objects"]
    bottom = objects.location[objects.type != "DontCare"]
    uv, _ = geometry.project(bottom, sample["P2"])
    return bottom, uv


def test_plane_read_from_planes_file_and_moved_by_flip_crop_resize(tilted_root):
    """The read plane contains the labels' bottom centres; after crop / resize / flip (each and
    all) the plane ray-cast through the new P2 at their new pixels gives back their depth."""
    source = KittiObjectSource(tilted_root, "all")
    sample = source[0]
    assert sample["plane"][1] < -0.9 and sample["plane"][2] < -0.3  # pitched down 20 degrees
    bottom, _ = road_points(sample)
    assert len(bottom) >= 1
    # labels are written with cm precision
    np.testing.assert_allclose(geometry.height_above_plane(bottom, sample["plane"]), 0, atol=0.01)
    chains = {
        "crop": [transforms.CropTop(40)],
        "resize": [transforms.Resize(96)],
        "flip": [transforms.HorizontalFlip()],
        "all": [transforms.CropTop(40), transforms.Resize(96), transforms.HorizontalFlip()],
    }
    for name, ops in chains.items():
        out = transforms.Compose(ops)(sample)
        bottom, uv = road_points(out)
        z = geometry.ground_depth(uv[:, 1], out["P2"], u=uv[:, 0], plane=out["plane"])
        np.testing.assert_allclose(z, bottom[:, 2], rtol=3e-3, err_msg=name)  # (cm labels)
        if name in ("flip", "all"):
            assert out["plane"][0] == -sample["plane"][0]
        else:
            np.testing.assert_array_equal(out["plane"], sample["plane"])


def test_generated_plane_is_the_scene_ground(tilted_root):
    from gac_jax.data.synthetic.frame import make_frame

    frame = make_frame(3, 1, (188, 621), pitch=np.radians(20.0))
    np.testing.assert_allclose(
        KittiObjectSource(tilted_root, "all")[1]["plane"], frame.plane, atol=1e-11
    )


def test_ground_depth_of_a_tilted_plane_is_the_ray_plane_depth():
    plane = tilted(20.0, 5.0)
    z = geometry.ground_depth_map((375, 1242), KITTI_P2, plane=plane)
    v, u = 300, 100
    C = geometry.camera_center(KITTI_P2)
    X = geometry.unproject(np.array([u, v], float), np.array(z[v, u] + KITTI_P2[2, 3]), KITTI_P2)
    assert geometry.height_above_plane(X, plane) == pytest.approx(0.0, abs=1e-9)
    assert X[2] == pytest.approx(z[v, u]) and np.all(np.isfinite(z[200:])) and C[2] < 0
    level = geometry.ground_depth_map((375, 1242), KITTI_P2)
    np.testing.assert_array_equal(np.isinf(level[:173]), True)


def test_ground_plane_baseline_uses_each_frames_plane():
    """NaN = a frame without a plane: the predictor's level plane."""
    from gac_jax.evaluation.depth_evaluator import GroundPlanePredictor

    A = transforms.resize_affine((375, 1242), (188, 621))
    batch = {
        "P2": np.stack([A @ KITTI_P2] * 2).astype(np.float32),
        "image_transform": np.stack([A] * 2).astype(np.float32),
        "original_size": np.array([[375, 1242]] * 2),
        "plane": np.stack([tilted(10.0, 3.0), np.full(4, np.nan)]).astype(np.float32),
    }
    pitched, level = GroundPlanePredictor(1.5, 80.0)(batch)
    P0 = np.linalg.solve(A.astype(np.float32), batch["P2"][0].astype(np.float64))
    for got, plane in ((pitched, tilted(10.0, 3.0)), (level, geometry.level_plane(1.5))):
        want = np.minimum(geometry.ground_depth_map((375, 1242), P0, plane=plane), 80.0)
        np.testing.assert_allclose(got, want, rtol=1e-5)
    assert np.ptp(pitched[300]) > 0.1 and np.ptp(level[300]) == 0  # the roll tilts each row


def test_predict_cli_source_reads_the_kitti_layouts_plane(tilted_root):
    from gac_jax.cli.predict import ImageSource

    image = tilted_root / "training" / "image_2" / "000000.png"
    calib = tilted_root / "training" / "calib" / "000000.txt"
    sample = ImageSource([image], [calib])[0]
    np.testing.assert_array_equal(
        sample["plane"], read_plane(tilted_root / "training/planes/000000.txt")
    )
    (tilted_root / "alone").mkdir()
    alone = tilted_root / "alone" / "000000.png"
    alone.write_bytes(image.read_bytes())
    assert "plane" not in ImageSource([alone], [calib])[0]  # then the config's level plane


@pytest.mark.parametrize("variant, kept", [("tiny", True), ("tiny,fixedplane", False)])
def test_use_planes_false_gives_the_level_plane_everywhere(tilted_root, variant, kept):
    """``data.use_planes = False`` (variant ``fixedplane``): the train and eval transforms drop
    the file's plane, so the loader falls back to the config's level plane."""
    from pathlib import Path

    from gac_jax.builders import detect3d as builders
    from gac_jax.config import load_config
    from gac_jax.data.loader import plane_array

    repo = Path(__file__).resolve().parents[1]
    c = load_config(str(repo / "configs" / f"detect3d_default.py:{variant}"))
    sample = KittiObjectSource(tilted_root, "all")[0]
    for transform in (builders.train_transform(c), builders.eval_transform(c)):
        out = transform(dict(sample))
        assert ("plane" in out) == kept
        want = sample["plane"] if kept else geometry.level_plane(c.model.gac.camera_height)
        if kept:  # (the train transform may flip: a -> -a)
            assert np.allclose(np.abs(plane_array(out)), np.abs(want), atol=1e-6)
        else:
            np.testing.assert_allclose(plane_array(out, c.model.gac.camera_height), want)
