"""hloc's HDF5 local-features files (dqm.vision.hloc): round trips, hloc's own layout, errors."""
import sys

import numpy as np
import pytest

h5py = pytest.importorskip("h5py", reason="h5py is not installed (optional: pip install 'dqm[colmap]')")

from conftest import assert_consistent  # noqa: E402

import dqm  # noqa: E402
from dqm import InputError  # noqa: E402
from dqm.io import FeatureSet  # noqa: E402
from dqm.vision import hloc  # noqa: E402


def _feature_set(counts=(5, 0, 7), dim=16, seed=0, names=None):
    rng = np.random.default_rng(seed)
    n = sum(counts)
    ids = np.repeat(np.arange(len(counts)), counts)
    kp = np.c_[rng.uniform(0, 640, (n, 2)), rng.uniform(1, 20, n), rng.uniform(0, 360, n)].astype(np.float32)
    names = names or [f"img{k}.jpg" for k in range(len(counts))]
    return FeatureSet(rng.normal(size=(n, dim)).astype(np.float32), ids, kp, np.array(names))


def _write_hloc(path, images, dtype=np.float16):
    """A file in exactly hloc's layout (as extract_features.main with as_half writes it)."""
    with h5py.File(str(path), "w") as fd:
        for name, (kp, desc) in images.items():
            grp = fd.create_group(name)
            grp.create_dataset("keypoints", data=np.asarray(kp, dtype))
            grp.create_dataset("descriptors", data=np.asarray(desc, dtype).T)  # D x N
            grp.create_dataset("scores", data=np.ones(len(kp), dtype))
            grp.create_dataset("image_size", data=np.array([640, 480]))
            grp["keypoints"].attrs["uncertainty"] = 2.0


def test_round_trip_is_identical(tmp_path):
    fs = _feature_set()
    out = hloc.write_h5_features(tmp_path / "feats.h5", fs)
    with h5py.File(out, "r") as fd:
        g = fd["img2.jpg"]
        assert g["descriptors"].shape == (16, 7) and g["descriptors"].dtype == np.float32
        assert g["keypoints"].shape == (7, 2) and g["scores"].shape == (7,)
        assert fd["img1.jpg"]["descriptors"].shape == (16, 0)  # an image without features keeps its group
    back = hloc.read_h5_features(out)
    np.testing.assert_array_equal(back.descriptors, fs.descriptors)
    np.testing.assert_array_equal(back.keypoints, fs.keypoints)
    np.testing.assert_array_equal(back.image_ids, fs.image_ids)
    assert back.image_names.tolist() == fs.image_names.tolist()
    assert back.descriptors.dtype == np.float32 and back.keypoints.shape == (len(fs), 4)


def test_read_orders_images_by_name_and_image_dir_prefixes(tmp_path):
    fs = _feature_set(counts=(3, 4), names=["z.png", "a.png"])
    hloc.write_h5_features(tmp_path / "f.h5", fs)
    back = hloc.read_h5_features(tmp_path / "f.h5", image_dir=tmp_path / "images")
    assert back.image_names.tolist() == [str(tmp_path / "images" / "a.png"), str(tmp_path / "images" / "z.png")]
    np.testing.assert_array_equal(back.image_ids, [0, 0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(back.descriptors, np.r_[fs.descriptors[3:], fs.descriptors[:3]])
    only = hloc.read_h5_features(tmp_path / "f.h5", names=["z.png"])
    np.testing.assert_array_equal(only.descriptors, fs.descriptors[:3])
    with pytest.raises(InputError, match="no image named 'b.png'"):
        hloc.read_h5_features(tmp_path / "f.h5", names=["b.png"])


def test_names_with_slashes_are_nested_groups(tmp_path):
    names = ["seq1/img0.png", "seq1/img1.png", "seq2/sub/img0.png"]
    fs = _feature_set(counts=(2, 3, 4), names=names)
    hloc.write_h5_features(tmp_path / "f.h5", fs)
    with h5py.File(tmp_path / "f.h5", "r") as fd:
        assert isinstance(fd["seq2"], h5py.Group) and isinstance(fd["seq2/sub"], h5py.Group)
        assert fd["seq2/sub/img0.png/keypoints"].shape == (4, 2)
    assert hloc.list_image_names(tmp_path / "f.h5") == names
    back = hloc.read_h5_features(tmp_path / "f.h5")
    assert back.image_names.tolist() == names
    np.testing.assert_array_equal(back.descriptors, fs.descriptors)


def test_names_relative_to_image_dir_and_image_size_from_files(tmp_path):
    import cv2

    root = tmp_path / "images"
    (root / "a").mkdir(parents=True)
    cv2.imwrite(str(root / "a" / "x.png"), np.zeros((30, 50), np.uint8))
    cv2.imwrite(str(root / "y.png"), np.zeros((20, 10), np.uint8))
    fs = _feature_set(counts=(2, 2), names=[str(root / "a" / "x.png"), str(root / "y.png")])
    hloc.write_h5_features(tmp_path / "f.h5", fs, image_dir=root)
    with h5py.File(tmp_path / "f.h5", "r") as fd:
        assert fd["a/x.png/image_size"][()].tolist() == [50, 30]  # width, height
        assert fd["y.png/image_size"][()].tolist() == [10, 20]
    with pytest.raises(InputError, match="absolute|relative path"):
        hloc.write_h5_features(tmp_path / "g.h5", fs)  # absolute names without image_dir
    with pytest.raises(InputError, match="not inside the image folder"):
        hloc.write_h5_features(tmp_path / "g.h5", fs, image_dir=tmp_path / "elsewhere")
    hloc.write_h5_features(tmp_path / "g.h5", fs, names=["p.png", "q.png"], image_sizes=[[1, 2], [3, 4]])
    with h5py.File(tmp_path / "g.h5", "r") as fd:
        assert fd["q.png/image_size"][()].tolist() == [3, 4]


def test_reads_a_file_in_hlocs_own_layout(tmp_path):
    rng = np.random.default_rng(1)
    images = {}
    for name, n in (("db/b.jpg", 6), ("db/a.jpg", 4), ("query/q.jpg", 5)):
        desc = rng.normal(size=(n, 256))
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        images[name] = (rng.uniform(0, 600, (n, 2)), desc)
    _write_hloc(tmp_path / "feats-superpoint-n4096-r1024.h5", images)
    fs = hloc.read_h5_features(tmp_path / "feats-superpoint-n4096-r1024.h5")
    order = ["db/a.jpg", "db/b.jpg", "query/q.jpg"]
    assert fs.image_names.tolist() == order
    np.testing.assert_array_equal(np.bincount(fs.image_ids), [4, 6, 5])
    assert fs.descriptors.shape == (15, 256) and fs.descriptors.dtype == np.float32
    want_desc = np.concatenate([images[n][1].astype(np.float16).astype(np.float32) for n in order])
    want_xy = np.concatenate([images[n][0].astype(np.float16).astype(np.float32) for n in order])
    np.testing.assert_array_equal(fs.descriptors, want_desc)
    np.testing.assert_array_equal(fs.keypoints[:, :2], want_xy)  # same pixel convention: no shift
    assert (fs.keypoints[:, 2] == hloc.DEFAULT_SIZE).all() and (fs.keypoints[:, 3] == hloc.DEFAULT_ANGLE).all()


def test_reads_sift_scales_and_orientations(tmp_path):
    with h5py.File(tmp_path / "feats-sift.h5", "w") as fd:
        g = fd.create_group("a.jpg")
        g["keypoints"] = np.array([[1.0, 2.0], [3.0, 4.0]], np.float16)
        g["descriptors"] = np.ones((128, 2), np.float16)
        g["scales"] = np.array([1.5, 2.5], np.float16)
        g["oris"] = np.array([-90.0, 45.0], np.float16)
    fs = hloc.read_h5_features(tmp_path / "feats-sift.h5")
    np.testing.assert_array_equal(fs.keypoints, [[1, 2, 1.5, -90], [3, 4, 2.5, 45]])


def test_features_feed_quickmatch_consistently(tmp_path):
    rng = np.random.default_rng(3)
    points = rng.normal(size=(40, 64))
    images = {}
    for k in range(4):
        seen = rng.permutation(40)[:30]
        desc = points[seen] + 0.05 * rng.normal(size=(30, 64))
        images[f"seq/img{k}.png"] = (rng.uniform(0, 500, (30, 2)), desc)
    _write_hloc(tmp_path / "features.h5", images)
    fs = hloc.read_h5_features(tmp_path / "features.h5")
    result = dqm.quickmatch(fs.descriptors, fs.image_ids)
    assert_consistent(result.labels, fs.image_ids)
    assert len(np.unique(result.labels)) < len(fs)  # features of one point were matched across images


def test_file_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        hloc.read_h5_features(tmp_path / "absent.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(InputError, match="not an HDF5 file"):
        hloc.read_h5_features(tmp_path / "text.h5")
    with pytest.raises(InputError, match="not an HDF5 file"):
        hloc.read_h5_features(tmp_path)
    with h5py.File(tmp_path / "empty.h5", "w") as fd:
        fd.create_group("just/groups")
    with pytest.raises(InputError, match="no image groups"):
        hloc.read_h5_features(tmp_path / "empty.h5")


def test_group_errors(tmp_path):
    def check(pattern, **datasets):
        p = tmp_path / "bad.h5"
        with h5py.File(p, "w") as fd:
            good = fd.create_group("good.jpg")
            good["keypoints"] = np.zeros((2, 2), np.float32)
            good["descriptors"] = np.zeros((8, 2), np.float32)
            grp = fd.create_group("dir/bad.jpg")
            for key, value in datasets.items():
                grp[key] = value
        with pytest.raises(InputError, match=pattern) as info:
            hloc.read_h5_features(p)
        assert "\n" not in str(info.value)

    check("'dir/bad.jpg' has no 'keypoints'", descriptors=np.zeros((8, 2)))
    check("'dir/bad.jpg' has no 'descriptors'", keypoints=np.zeros((2, 2)))
    check("global-descriptor file", global_descriptor=np.zeros(4096))
    check("descriptor dimension differs between images: 16 in 'dir/bad.jpg', 8 in 'good.jpg'",
          keypoints=np.zeros((2, 2)), descriptors=np.zeros((16, 2)))
    nan = np.zeros((8, 3))
    nan[2, 1] = np.nan
    check("descriptors contain NaN in 1 feature\\(s\\), first at keypoint 1", keypoints=np.zeros((3, 2)),
          descriptors=nan)
    check("descriptors contain inf", keypoints=np.zeros((3, 2)), descriptors=np.full((8, 3), np.inf, np.float16))
    check("3 keypoints but descriptors of shape \\(8, 4\\)", keypoints=np.zeros((3, 2)), descriptors=np.zeros((8, 4)))
    check("stored N x D\\? hloc's layout is D x N", keypoints=np.zeros((3, 2)), descriptors=np.zeros((3, 8)))
    check("keypoints must be \\(N, 2\\)", keypoints=np.zeros(3), descriptors=np.zeros((8, 3)))
    check("keypoints contain NaN", keypoints=np.full((3, 2), np.nan), descriptors=np.zeros((8, 3)))
    check("scales must have one value per keypoint", keypoints=np.zeros((3, 2)), descriptors=np.zeros((8, 3)),
          scales=np.zeros(2))


def test_write_errors(tmp_path):
    fs = _feature_set()
    hloc.write_h5_features(tmp_path / "f.h5", fs)
    with pytest.raises(InputError, match="exists; pass overwrite=True"):
        hloc.write_h5_features(tmp_path / "f.h5", fs)
    other = _feature_set(seed=5)
    hloc.write_h5_features(tmp_path / "f.h5", other, overwrite=True)
    np.testing.assert_array_equal(hloc.read_h5_features(tmp_path / "f.h5").descriptors, other.descriptors)
    with pytest.raises(InputError, match="no keypoints"):
        hloc.write_h5_features(tmp_path / "g.h5", FeatureSet(fs.descriptors, fs.image_ids, None, fs.image_names))
    with pytest.raises(InputError, match="no image_names: pass names="):
        hloc.write_h5_features(tmp_path / "g.h5", FeatureSet(fs.descriptors, fs.image_ids, fs.keypoints))
    with pytest.raises(InputError, match="image ids go up to 2"):
        hloc.write_h5_features(tmp_path / "g.h5", fs, names=["a.jpg", "b.jpg"])
    with pytest.raises(InputError, match="same name"):
        hloc.write_h5_features(tmp_path / "g.h5", fs, names=["a.jpg", "b.jpg", "a.jpg"])
    with pytest.raises(InputError, match="relative path"):
        hloc.write_h5_features(tmp_path / "g.h5", fs, names=["a.jpg", "b//c.jpg", "../d.jpg"])
    assert not (tmp_path / "g.h5").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["f.h5"]  # no temporary file left behind


def test_missing_h5py_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(InputError, match=r"pip install 'dqm\[colmap\]'"):
        hloc.read_h5_features(tmp_path / "f.h5")
    with pytest.raises(InputError, match=r"pip install 'dqm\[colmap\]'"):
        hloc.write_h5_features(tmp_path / "f.h5", _feature_set())
