"""Controls files: exact round trips for .npy and .csv, one clear error per bad file."""

from __future__ import annotations

import numpy as np
import pytest

from hybridoc import ControlsError, Disc, Scene
from hybridoc.io import load_controls, save_controls

N = 6


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(
        horizon=1.0,
        steps=N,
        discs=(
            Disc(name="striker", position=(0.0, 0.0), radius=0.2, actuated=True),
            Disc(name="goal", position=(1.0, 0.0), radius=0.2, target=(2.0, 0.0)),
        ),
    )


@pytest.fixture
def values() -> np.ndarray:
    rng = np.random.default_rng(1)
    u = rng.normal(size=(N, 2)) * np.array([1e-7, 1e5])
    u[0, 0] = 0.1 + 0.2  # not a short decimal
    u[1, 1] = -0.0
    return u


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
def test_round_trip_exact(tmp_path, scene, values, suffix):
    path = save_controls(tmp_path / "sub" / f"u{suffix}", values, scene.control_labels())
    back = load_controls(path, scene)
    assert back.dtype == np.float64 and back.shape == (N, 2)
    assert back.tobytes() == values.tobytes()
    # a HybridOCP is accepted as well as a scene
    assert np.array_equal(load_controls(path, scene.to_ocp()), values)


def test_csv_header_written_and_optional(tmp_path, scene, values):
    path = save_controls(tmp_path / "u.csv", values, scene.control_labels())
    assert path.read_text().splitlines()[0] == "striker.ux,striker.uy"
    bare = tmp_path / "bare.csv"
    bare.write_text("\n".join(f"{float(a)!r}, {float(b)!r}" for a, b in values) + "\n\n")
    assert np.array_equal(load_controls(bare, scene), values)


def test_csv_header_columns_found_by_label(tmp_path, scene, values):
    # before: the header was skipped and the columns used in file order, so swapped columns
    # silently swapped ux and uy
    swapped = tmp_path / "swapped.csv"
    rows = "\n".join(f"{float(b)!r},{float(a)!r}" for a, b in values)
    swapped.write_text("striker.uy, striker.ux\n" + rows + "\n")
    assert np.array_equal(load_controls(swapped, scene), values)
    quoted = tmp_path / "quoted.csv"
    quoted.write_text('"striker.uy","striker.ux"\n' + rows + "\n")
    assert np.array_equal(load_controls(quoted, scene), values)
    # a spreadsheet's "CSV UTF-8" starts with a byte-order mark
    bom = tmp_path / "bom.csv"
    bom.write_text("striker.uy,striker.ux\n" + rows + "\n", encoding="utf-8-sig")
    assert np.array_equal(load_controls(bom, scene), values)
    # save_controls' default names u0, u1, ... keep the file's order
    generic = save_controls(tmp_path / "generic.csv", values)
    assert generic.read_text().startswith("u0,u1\n")
    assert np.array_equal(load_controls(generic, scene), values)


def _write(tmp_path, name, content):
    p = tmp_path / name
    if isinstance(content, np.ndarray):
        np.save(p, content, allow_pickle=True)
    elif isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    return p


GOOD_ROWS = "1.0,2.0\n" * N


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("missing.npy", None, "does not exist"),
        ("u.txt", "1,2\n", "unsupported file type '.txt'"),
        (
            "short.npy",
            np.zeros((N - 1, 2)),
            r"expected shape \(6, 2\).*striker.ux, striker.uy.*"
            r"got shape \(5, 2\)",
        ),
        ("wide.csv", "a,b,c\n" + "1,2,3\n" * N, r"expected shape \(6, 2\).*got shape \(6, 3\)"),
        ("nan.npy", np.where(np.eye(N, 2) > 0, np.nan, 0.0), "non-finite value nan at row 0"),
        (
            "inf.csv",
            "striker.ux,striker.uy\n" + "1,2\n" * 3 + "1,inf\n" + "1,2\n" * 2,
            r"non-finite value inf at row 3 \(striker.uy\)",
        ),
        (
            "text.csv",
            "ux,uy\n" + "1,2\n" * 2 + "1,two\n" + "1,2\n" * 3,
            "line 4: 'two' is not a number",
        ),
        ("ragged.csv", "1,2\n1,2,3\n" + "1,2\n" * 4, "line 2 has 3 values"),
        ("empty.csv", "\n\n", "empty"),
        ("header_only.csv", "ux,uy\n", "no data rows"),
        ("header.csv", "ux,uy,uz\n" + GOOD_ROWS, "header has 3 columns"),
        # a header names the columns: one that names others is an error, not ignored
        ("short_names.csv", "ux,uy\n" + GOOD_ROWS, "unknown 'ux', 'uy'; missing 'striker.ux'"),
        ("typo.csv", "striker.uy,striker.ix\n" + GOOD_ROWS, "unknown 'striker.ix'"),
        ("repeated.csv", "striker.uy,striker.uy\n" + GOOD_ROWS, "repeated 'striker.uy'"),
        ("garbage.npy", b"this is not an npy file", "not a readable .npy"),
        ("objects.npy", np.array([[1, "a"]] * N, dtype=object), "not a readable .npy"),
        ("strings.npy", np.array([["1", "2"]] * N), "numeric array"),
    ],
)
def test_bad_files(tmp_path, scene, name, content, match):
    path = tmp_path / name if content is None else _write(tmp_path, name, content)
    with pytest.raises(ControlsError, match=match) as info:
        load_controls(path, scene)
    assert "\n" not in str(info.value)
    assert name in str(info.value)


def test_save_errors(tmp_path, values):
    with pytest.raises(ControlsError, match="use a .npy or .csv"):
        save_controls(tmp_path / "u.txt", values)
    with pytest.raises(ControlsError, match="1 labels given for 2"):
        save_controls(tmp_path / "u.csv", values, ["only"])
    with pytest.raises(ControlsError, match="2-D"):
        save_controls(tmp_path / "u.npy", values.ravel())
