"""Lab formats (issue 18): MATLAB .mat v5 and v7.3, HDF5, LabVIEW TDMS and UFF 58. Every
fixture is written by the format's own library (scipy.io, h5py, npTDMS, pyuff) from a bundled
CSV, and each fits to the CSV's estimates."""

import json
import sys

import numpy as np
import pytest

import hamid
from hamid.data import lab_formats
from hamid.data import readers as hio
from hamid.errors import DataError

h5py = pytest.importorskip("h5py")
nptdms = pytest.importorskip("nptdms")
pyuff = pytest.importorskip("pyuff")
sio = pytest.importorskip("scipy.io")

SAMPLE = "sample_data/duffing.csv"
NAMES = ["trajectory", "t", "x", "v"]


@pytest.fixture(scope="module")
def sample():
    columns, metadata = hio.read_columns(SAMPLE)
    assert list(columns) == NAMES
    return columns, metadata


@pytest.fixture(scope="module")
def truth():
    """The CSV's estimates, with the model its metadata names."""
    return hamid.fit(SAMPLE).estimates


def _same(result, truth):
    assert result.estimates.keys() == truth.keys()
    for name, value in truth.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-10, abs=1e-14)


def _read(source):
    columns, metadata = hio.read_columns(source)
    return columns, metadata


# --- MATLAB v5 (scipy.io) --------------------------------------------------------------------


def test_mat_v5_vectors_with_metadata(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.mat"
    sio.savemat(path, {**columns, "hamid": json.dumps(metadata), "note": "bench 3",
                       "fs": 20.0})
    got, meta = _read(path)
    assert list(got) == NAMES and meta == metadata   # scalars and text are not columns
    for name in NAMES:
        assert np.array_equal(got[name], columns[name])
    _same(hamid.fit(str(path)), truth)


def test_mat_v5_struct_and_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.mat"
    fields = {"trajectory": columns["trajectory"], "time": columns["t"],
              "pos": columns["x"], "vel": columns["v"]}
    sio.savemat(path, {"run": fields})
    assert list(_read(path)[0]) == ["trajectory", "time", "pos", "vel"]
    _same(hamid.fit(str(path), "duffing", columns={"x": "pos", "v": "vel"}, time="time"),
          truth)


def test_mat_v5_array_with_column_names(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.mat"
    table = np.column_stack([columns[name] for name in NAMES]).astype(float)
    names = np.array(NAMES, dtype=object)   # a cell array of text
    sio.savemat(path, {"data": table, "data_columns": names, "other": np.arange(3.0)})
    got, _ = _read(f"{path}:data")   # only that variable
    assert list(got) == NAMES
    _same(hamid.fit(f"{path}:data", "duffing"), truth)
    sio.savemat(path, {"data": table})
    assert list(_read(path)[0]) == ["data_1", "data_2", "data_3", "data_4"]


def test_mat_v5_unequal_lengths_and_unknown_variable(tmp_path):
    path = tmp_path / "run.mat"
    sio.savemat(path, {"t": np.arange(5.0), "x": np.arange(4.0)})
    with pytest.raises(DataError, match=rf"^{path}: the columns have different lengths "
                                        r"\('t' 5, 'x' 4\)$"):
        _read(path)
    with pytest.raises(DataError, match=rf"^{path}:y: no variable 'y' \(the file has 't', "
                                        r"'x'\)$"):
        _read(f"{path}:y")


def test_mat_damaged(tmp_path):
    path = tmp_path / "run.mat"
    path.write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 20)
    with pytest.raises(DataError, match=rf"^{path}: is not a readable MATLAB file \(.+\)$"):
        _read(path)


# --- MATLAB v7.3 (HDF5, written as MATLAB does: a 512-byte header, arrays column-major) --------


def _write_mat73(path, variables):
    with h5py.File(path, "w", userblock_size=512) as file:
        for name, value in variables.items():
            if isinstance(value, str):
                codes = np.frombuffer(value.encode("utf-16-le"), dtype="<u2")
                dataset = file.create_dataset(name, data=codes.reshape(-1, 1))
                dataset.attrs["MATLAB_class"] = np.bytes_("char")
            else:
                value = np.asarray(value, dtype=float)
                dataset = file.create_dataset(name, data=np.atleast_2d(value))   # 1 x n
                dataset.attrs["MATLAB_class"] = np.bytes_("double")
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Nov 23 10:00:00 2026 " \
        b"HDF5 schema 1.00 ."
    with open(path, "r+b") as stream:
        stream.write(header.ljust(116) + b"\x00" * 8 + b"\x00\x02IM")


def test_mat_v73(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run73.mat"
    _write_mat73(path, {**columns, "hamid": json.dumps(metadata)})
    with pytest.raises(NotImplementedError):   # scipy itself cannot: h5py reads it
        sio.loadmat(path)
    got, meta = _read(path)
    assert sorted(got) == sorted(NAMES) and meta == metadata
    _same(hamid.fit(str(path)), truth)


def test_mat_v73_struct(tmp_path, sample, truth):
    """A MATLAB struct is an HDF5 group; its vector fields are the columns."""
    columns, _ = sample
    path = tmp_path / "run73.mat"
    _write_mat73(path, {"fs": 20.0})
    with h5py.File(path, "a") as file:
        group = file.create_group("run")
        group.attrs["MATLAB_class"] = np.bytes_("struct")
        for name in NAMES:
            group.create_dataset(name, data=np.atleast_2d(columns[name].astype(float)))
    got, meta = _read(path)
    assert sorted(got) == sorted(NAMES) and meta is None   # fs (1 x 1) is not a column
    assert np.array_equal(got["x"], columns["x"])
    _same(hamid.fit(str(path), "duffing"), truth)


# --- HDF5 ----------------------------------------------------------------------------------


def test_hdf5_group_of_vectors(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("bench/run1")
        for name in NAMES:
            group.create_dataset(name, data=columns[name])
        file.attrs["hamid"] = json.dumps(metadata)
    got, meta = _read(f"{path}:/bench/run1")
    assert sorted(got) == sorted(NAMES) and meta == metadata
    _same(hamid.fit(f"{path}:/bench/run1"), truth)
    with pytest.raises(DataError, match=rf"^{path}: no 1-D numeric datasets in '/' \(it "
                                        r"holds 'bench'\); give .+:/path/to/dataset$"):
        _read(path)


def test_hdf5_compound_dataset(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.hdf5"
    table = np.empty(len(columns["t"]), dtype=[("trajectory", "i8"), ("time", "f8"),
                                                ("pos", "f8"), ("vel", "f8")])
    for field, name in zip(table.dtype.names, NAMES, strict=True):
        table[field] = columns[name]
    with h5py.File(path, "w") as file:
        file.create_dataset("data/table", data=table)
    source = f"{path}:/data/table"
    assert list(_read(source)[0]) == ["trajectory", "time", "pos", "vel"]
    _same(hamid.fit(source, "duffing", columns={"x": "pos", "v": "vel"}, time="time"), truth)


def test_hdf5_2d_array_alone_in_the_file(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        dataset = file.create_dataset("samples",
                                      data=np.column_stack([columns[n] for n in NAMES]))
        dataset.attrs["columns"] = NAMES
    assert list(_read(path)[0]) == NAMES   # the file's only dataset, its named columns
    _same(hamid.fit(str(path), "duffing"), truth)
    with pytest.raises(DataError, match=rf"^{path}:/nothing: no dataset or group "
                                        r"'/nothing' in "):
        _read(f"{path}:/nothing")


def test_hdf5_read_in_chunks_gives_the_same_fit(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        for name in NAMES:
            file.create_dataset(name, data=columns[name])
        file.attrs["hamid"] = json.dumps(metadata)
    table = hio.TableChunks(path)
    assert table.columns == sorted(NAMES) or set(table.columns) == set(NAMES)
    x = np.concatenate([chunk["x"] for chunk in table.chunks(["x"], 128)])
    assert np.array_equal(x, columns["x"])
    streamed = hamid.fit(SAMPLE, chunk_rows=128).estimates
    got = hamid.fit(str(path), chunk_rows=128).estimates
    for name, value in streamed.items():
        assert got[name] == pytest.approx(value, rel=1e-10)


def test_hdf5_not_hdf5(tmp_path):
    path = tmp_path / "run.h5"
    path.write_text("t,x\n0,1\n")
    with pytest.raises(DataError, match=rf"^{path}: is not a readable HDF5 file \(.+\)$"):
        _read(path)


# --- TDMS ----------------------------------------------------------------------------------


def _write_tdms(path, groups, root_properties=None):
    objects = [nptdms.RootObject(properties=root_properties or {})]
    for group, channels in groups.items():
        objects.append(nptdms.GroupObject(group))
        for name, (data, properties) in channels.items():
            objects.append(nptdms.ChannelObject(group, name, data, properties=properties))
    with nptdms.TdmsWriter(path) as writer:
        writer.write_segment(objects)


def test_tdms_group_channels(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.tdms"
    _write_tdms(path, {"Measured": {name: (columns[name], {}) for name in NAMES},
                       "Empty": {}}, {"hamid": json.dumps(metadata)})
    got, meta = _read(path)
    assert list(got) == NAMES and meta == metadata
    _same(hamid.fit(str(path)), truth)
    _same(hamid.fit(f"{path}:Measured", "duffing",
                    columns={"x": "x", "v": "v"}), truth)


def test_tdms_several_groups_and_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.tdms"
    renamed = {"trajectory": "trajectory", "t": "Time", "x": "Disp", "v": "Vel"}
    _write_tdms(path, {"Raw": {"a": (np.arange(3.0), {})},
                       "Run": {renamed[n]: (columns[n], {}) for n in NAMES}})
    with pytest.raises(DataError, match=rf"^{path}: has 2 groups with channels \('Raw', "
                                        r"'Run'\); give .+:GROUP$"):
        _read(path)
    _same(hamid.fit(f"{path}:Run", "duffing", columns={"x": "Disp", "v": "Vel"},
                    time="Time"), truth)


def test_tdms_waveform_channels_get_time(tmp_path):
    path = tmp_path / "wave.tdms"
    timing = {"wf_start_offset": 0.0, "wf_increment": 0.01}
    _write_tdms(path, {"g": {"x": (np.sin(np.arange(50) * 0.01), timing),
                             "v": (np.cos(np.arange(50) * 0.01), timing)}})
    got, _ = _read(path)
    assert list(got) == ["t", "x", "v"]
    assert np.allclose(got["t"], np.arange(50) * 0.01, rtol=0, atol=1e-15)


# --- UFF 58 ----------------------------------------------------------------------------------


def _write_uff(path, columns, names):
    # ASCII records (pyuff 2.5 does not read back its binary ones with an uneven abscissa):
    # twelve significant digits.
    sets = []
    for k in np.unique(columns["trajectory"]):
        rows = columns["trajectory"] == k
        for name in names:
            sets.append(pyuff.prepare_58(
                binary=0, id1=name, func_type=1, rsp_node=1, rsp_dir=1, ref_node=0,
                ref_dir=0, abscissa_spacing=0, ord_data_type=4, abscissa_spec_data_type=17,
                ordinate_spec_data_type=0, orddenom_spec_data_type=0, z_axis_spec_data_type=0,
                data=np.asarray(columns[name][rows], dtype=float),
                x=np.asarray(columns["t"][rows], dtype=float)))
    pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")


def test_uff58_records_are_columns(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.uff"
    _write_uff(path, columns, ["x", "v"])
    got, meta = _read(path)
    assert list(got) == ["trajectory", "t", "x", "v"] and meta is None
    for name in NAMES:
        assert np.allclose(got[name], columns[name], rtol=1e-11, atol=1e-13)
    _same(hamid.fit(str(path), "duffing"), truth)


def test_uff58_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.unv"
    renamed = {**columns, "disp": columns["x"], "vel": columns["v"]}
    _write_uff(path, renamed, ["disp", "vel"])
    _same(hamid.fit(str(path), "duffing", columns={"x": "disp", "v": "vel"}), truth)


# --- missing libraries, names --------------------------------------------------------------


@pytest.mark.parametrize(("module", "suffix", "package"),
                         [("h5py", ".h5", "h5py"), ("nptdms", ".tdms", "npTDMS"),
                          ("pyuff", ".uff", "pyuff"), ("scipy.io", ".mat", "scipy")])
def test_missing_library_is_one_line(tmp_path, monkeypatch, module, suffix, package):
    path = tmp_path / f"run{suffix}"
    path.write_bytes(b"\x00" * 16)
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(DataError, match=rf"^{path}: reading \S+ files needs the {package} "
                                        r"package: pip install 'hamid\[lab\]'$"):
        _read(path)


def test_missing_library_through_the_cli(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from hamid.cli.app import cli

    path = tmp_path / "run.h5"
    path.write_bytes(b"\x00" * 16)
    monkeypatch.setitem(sys.modules, "h5py", None)
    result = CliRunner().invoke(cli, ["fit", str(path)])
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert "pip install 'hamid[lab]'" in result.output


def test_split_names_the_inner_path(tmp_path):
    assert lab_formats.split("a/run.h5:/g/x") == ("a/run.h5", "/g/x")
    assert lab_formats.split("run.MAT:data") == ("run.MAT", "data")
    assert lab_formats.split("run.csv") == ("run.csv", None)
    assert lab_formats.format_of("run.h5:/g") == "hdf5" and lab_formats.format_of("a.csv") is None
    odd = tmp_path / "odd.h5:x.h5"   # a file whose name has the separator is that file
    odd.write_bytes(b"")
    assert lab_formats.split(str(odd)) == (str(odd), None)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match=rf"^{tmp_path}/no.h5: no such file$"):
        _read(f"{tmp_path}/no.h5:/g")


def test_cli_fits_an_hdf5_group_with_columns(tmp_path, sample, truth):
    """`hamid fit run.h5:/bench/run --columns ...` through the command line, JSON out."""
    from click.testing import CliRunner

    from hamid.cli.app import cli

    columns, _ = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("bench/run")
        for name, stored in zip(NAMES, ["trajectory", "t", "disp", "vel"], strict=True):
            group.create_dataset(stored, data=columns[name])
    result = CliRunner().invoke(cli, ["fit", f"{path}:/bench/run", "--model", "duffing",
                                      "--columns", "x=disp,v=vel", "--format", "json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    got = {p["name"]: p["estimate"] for p in report["parameters"]}
    for name, value in truth.items():
        assert got[name] == pytest.approx(value, rel=1e-10)
