"""Loaders of the public real-data benchmarks (EMPS, CED, ANL D3 Camry, EPA).

Each loader finds its files in a local folder, in this order:

1. ``data_dir`` (argument),
2. the environment variable ``BONDGRAPH_DATA``,
3. ``shared/data`` beside the project root (``<root>/../shared/data``), if
   it exists,

looking in ``<folder>/<dataset folder>/<file>`` and ``<folder>/<file>``.
Every file is checked against the SHA-256 recorded below (computed from the
publishers' files; ``verify=False`` skips the check for a modified copy); a
mismatch raises :class:`~bondgraph.errors.DataError` naming the file.

If no local folder was given (1 and 2) and the default folder lacks the
file, it is fetched from the publisher with :mod:`pooch` into a cache
(``BONDGRAPH_CACHE`` or pooch's OS cache): single files are checked by pooch
against their SHA-256; archives (``EMPS.zip``, ``FULLTEXT01.zip``), whose own
checksum is not recorded, are unpacked and every member used is checked
against its SHA-256. The download path cannot be exercised offline; tests
drive it with a local ``downloader``.

Sources (see ``/work/shared/data/*/README.md``)
----------------------------------------------
* EMPS — A. Janot, M. Gautier, M. Brunot, *Data Set and Reference Models of
  EMPS*, Nonlinear System Identification Benchmarks workshop, Eindhoven 2019;
  nonlinearbenchmark.org, ``EMPS.zip``.
* CED — T. Wigren, M. Schoukens, *Coupled Electric Drives Data Set and
  Reference Models*, Tech. Rep. 2017-024, Uppsala University; DiVA
  diva2:1165531, ``FULLTEXT01.zip``.
* ANL D3 — Argonne Downloadable Dynamometer Database, 2018 Toyota Camry XLE,
  1 Hz subset as shipped by NREL FASTSim (commit ``bd9111bb``).
* EPA — US EPA Test Car List, model year 2022 (``22-tstcar.csv``), as shipped
  by NREL FASTSim (commit ``bd9111bb``).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.io import loadmat

from bondgraph.data.record_io import read_table
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError

#: project root (the folder holding ``bondgraph/``)
PROJECT_ROOT = Path(__file__).resolve().parents[2]
#: environment variable naming a local data folder
ENV_DATA = "BONDGRAPH_DATA"
#: environment variable naming the download cache
ENV_CACHE = "BONDGRAPH_CACHE"

_FASTSIM = "https://raw.githubusercontent.com/NREL/fastsim/bd9111bb/python/fastsim/resources"


@dataclass(frozen=True)
class DataFile:
    """One file of a data set.

    Attributes
    ----------
    name : str
        Local file name.
    sha256 : str
        SHA-256 of the file (hex).
    url : str or None
        Where it is fetched: the file itself, or the archive holding it
        (``archive`` set). ``None``: not published (a local conversion).
    archive : str or None
        Name of the zip archive at ``url`` that holds the file.
    member : str or None
        File name inside the archive or at the URL, if it differs from
        ``name``.
    """

    name: str
    sha256: str
    url: str | None
    archive: str | None = None
    member: str | None = None


@dataclass(frozen=True)
class Dataset:
    """A public data set: folder name, landing page, citation, files."""

    key: str
    folder: str
    title: str
    landing: str
    citation: str
    files: dict[str, DataFile] = field(default_factory=dict)


def _files(*items: DataFile) -> dict[str, DataFile]:
    return {f.name: f for f in items}


_EMPS_ZIP = "https://www.nonlinearbenchmark.org/FILES/BENCHMARKS/EMPS/EMPS.zip"
_CED_ZIP = "https://uu.diva-portal.org/smash/get/diva2:1165531/FULLTEXT01.zip"
_SILVERBOX_ZIP = ("https://www.nonlinearbenchmark.org/FILES/BENCHMARKS/SILVERBOX/"
                  "SilverboxFiles.zip")

#: the data sets, their publishers and the SHA-256 of every file
DATASETS: dict[str, Dataset] = {
    "emps": Dataset(
        key="emps", folder="emps",
        title="EMPS: electro-mechanical positioning system (ONERA / LS2N), 1 kHz",
        landing="https://www.nonlinearbenchmark.org/benchmarks/emps",
        citation="A. Janot, M. Gautier, M. Brunot, Data Set and Reference Models of EMPS, "
                 "Workshop on Nonlinear System Identification Benchmarks, Eindhoven, 2019.",
        files=_files(
            DataFile("DATA_EMPS.mat",
                     "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
                     _EMPS_ZIP, archive="EMPS.zip"),
            DataFile("DATA_EMPS_PULSES.mat",
                     "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704",
                     _EMPS_ZIP, archive="EMPS.zip"),
            # lossless CSV conversions made for this project (not published)
            DataFile("emps_estimation.csv",
                     "72b8a6bb0cc329ae159eed18b59d28146a2343d40b3ae9217346b358373a6ed0", None),
            DataFile("emps_validation_pulses.csv",
                     "05b77eec10941db34e0f9e52103fe62ded7ecd29a40530af293036ec5a5a9ce6", None),
        )),
    "ced": Dataset(
        key="ced", folder="ced",
        title="CED: coupled electric drives (CE8), 50 Hz",
        landing="https://uu.diva-portal.org/smash/record.jsf?pid=diva2:1165531",
        citation="T. Wigren, M. Schoukens, Coupled Electric Drives Data Set and Reference "
                 "Models, Technical Report 2017-024, Dept. of Information Technology, Uppsala "
                 "University, 2017.",
        files=_files(
            DataFile("DATAPRBS.csv",
                     "aa48c6a6e2ea59608460a449ce75add95b572f61ae0f72ce89a64de5606b23b3",
                     _CED_ZIP, archive="FULLTEXT01.zip"),
            DataFile("DATAUNIF.csv",
                     "9114f637f22ca826f03f066270cf68bd8cad686739a7fa4b471c14ccdbf66889",
                     _CED_ZIP, archive="FULLTEXT01.zip"),
            DataFile("DATAPRBS.MAT",
                     "47d0825678d854d8a1bbcfb0ad1188026b853f69beb2067ea00cfd88d13dc4ca",
                     _CED_ZIP, archive="FULLTEXT01.zip"),
            DataFile("DATAUNIF.MAT",
                     "102c8d8012d6e850d50c13227b8c2280fe69f8bc4a845177f8bc3d761d152c89",
                     _CED_ZIP, archive="FULLTEXT01.zip"),
        )),
    "silverbox": Dataset(
        key="silverbox", folder="silverbox",
        title="Silverbox: electronic Duffing oscillator, fs = 610.35 Hz",
        landing="https://www.nonlinearbenchmark.org/benchmarks/silverbox",
        citation="T. Wigren, J. Schoukens, Three free data sets for development and "
                 "benchmarking in nonlinear system identification, European Control "
                 "Conference, Zurich, 2013, pp. 2933-2938.",
        files=_files(
            DataFile("SNLS80mV.mat",
                     "5c7413a52255af0cb4e2f93fb6903beb92b08965ba1e6ad0a6ffedfed8477ed4",
                     _SILVERBOX_ZIP, archive="SilverboxFiles.zip"),
            DataFile("SNLS80mV.csv",
                     "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1",
                     _SILVERBOX_ZIP, archive="SilverboxFiles.zip"),
            DataFile("Schroeder80mV.mat",
                     "ec5a9740a4789aa20b9d84f387424c0218e843844807b30b367c218778339fb6",
                     _SILVERBOX_ZIP, archive="SilverboxFiles.zip"),
            DataFile("Schroeder80mV.csv",
                     "b22cbcba9c59d9b4b1b379967b669dc32959e515b24784da3254505f8563e36c",
                     _SILVERBOX_ZIP, archive="SilverboxFiles.zip"),
        )),
    "camry": Dataset(
        key="camry", folder="anl_d3_camry2018",
        title="ANL D3 2018 Toyota Camry XLE on a chassis dynamometer (1 Hz subset)",
        landing="https://www.anl.gov/taps/d3-2018-toyota-camry-xle",
        citation="Argonne National Laboratory, Downloadable Dynamometer Database (D3), "
                 "2018 Toyota Camry XLE; 1 Hz subset from NREL FASTSim.",
        files=_files(*(
            DataFile(f"{n}.csv", h,
                     f"{_FASTSIM}/calibration_demo_assets/dyno_data/{n}%20Test%20Data.txt",
                     member=f"{n} Test Data.txt")
            for n, h in (
                ("61811011", "7b87d81590076aa505af0d504b4757a5be967ed17114be61e757110f74aaf0c5"),
                ("61811012", "a6bc4cd149d3e407f70fd7a0598242ac17e3e656cd2500e839a59aa85011f770"),
                ("61811013", "e577c2e779c3d1f55c21131f4866a146554b2bebcbc6e84f0db83f34a7fade37"),
                ("61811014", "3dedd8b143e47c2118b9427988b93707fb82dba4c9c7ad95fe786967220272c8"),
            )))),
    "epa": Dataset(
        key="epa", folder="epa_test_car_list_2022",
        title="US EPA Test Car List, model year 2022",
        landing="https://www.epa.gov/compliance-and-fuel-economy-data/"
                "data-cars-used-testing-fuel-economy",
        citation="US EPA, Data on Cars Used for Testing Fuel Economy, MY2022 (22-tstcar.csv).",
        files=_files(
            DataFile("22-tstcar.csv",
                     "fc5d0178be26eed9c1eac3598018b5808ca14ca1b22daef00106b43f3bcde65b",
                     f"{_FASTSIM}/epa_vehdb/22-tstcar.csv"),
        )),
}

#: EMPS constants as given by the data owners (README; the .mat files hold
#: the same values to more digits): drive gain gtau [N/V], position-loop
#: gain kp [1/s], velocity-loop gain kv [V/(m/s)]
EMPS_CONSTANTS: dict[str, float] = {"gtau": 35.15065, "kp": 160.18, "kv": 243.45}
#: CED sample period [s]
CED_TS = 0.02
#: CED runs: name -> (file, input column, output column, description)
CED_RUNS: dict[str, tuple[str, str, str, str]] = {
    "prbs_1": ("DATAPRBS", "u1", "z1", "PRBS, clock 5 samples, amplitude 1.0 V"),
    "prbs_2": ("DATAPRBS", "u2", "z2", "PRBS, clock 5 samples, amplitude 1.5 V"),
    "prbs_3": ("DATAPRBS", "u3", "z3", "PRBS, clock 5 samples, amplitude 0.5 V"),
    "unif_11": ("DATAUNIF", "u11", "z11", "PRBS with uniform random amplitude in [-1.5, 2.5] V"),
    "unif_12": ("DATAUNIF", "u12", "z12", "PRBS with uniform random amplitude in [-1.0, 3.0] V"),
}
#: Silverbox sample period [s]: fs = 10^7 / 2^14 Hz
SILVERBOX_TS = 2.0 ** 14 / 1e7
#: Silverbox record parts: name -> (0-based, half-open sample range of SNLS80mV,
#: description); the official split of nonlinearbenchmark.org (Silverbox())
SILVERBOX_PARTS: dict[str, tuple[int, int, str]] = {
    "full": (0, 131072, "the whole SNLS80mV record"),
    "train": (40650, 105712, "train + validation: the first 75 % of the multisine block"),
    "test_multisine": (105712, 127400, "test: multisine"),
    "test_arrow": (100, 40575, "test: the arrow (filtered Gaussian noise with rising RMS), "
                               "full, including the amplitude extrapolation"),
    "test_arrow_noextrap": (100, 32100, "test: the arrow without amplitude extrapolation"),
}
#: samples at the start of a Silverbox test part that may be used to
#: initialise the state (the published protocol scores the rest)
SILVERBOX_INIT_SAMPLES = 50
#: published simulation RMS errors on the arrow [mV] (secondary compilation,
#: see the data README): best linear approximation, physical-parameter model,
#: best black box
SILVERBOX_PUBLISHED_MV = {"bla": 13.7, "physical": 0.96, "best": 0.26}

#: ANL D3 Camry tests: id -> cycle (README)
CAMRY_TESTS: dict[str, str] = {
    "61811011": "cold-start UDDS, 628 s key-off soak, hot UDDS",
    "61811012": "hot-start UDDS",
    "61811013": "2 x HWFET",
    "61811014": "2 x US06",
}


# ------------------------------------------------------------ files and hashes
def sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


_VERIFIED: dict[tuple[str, int, int], str] = {}


def verify(path: str | Path, expected: str) -> Path:
    """Check a file's SHA-256.

    Raises
    ------
    DataError
        Naming the file, when the digest differs (corrupted, truncated or
        not the published version).
    """
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    digest = _VERIFIED.get(key) or sha256(path)
    if digest != expected:
        raise DataError(f"SHA-256 mismatch: expected {expected}, got {digest}; the file is "
                        f"corrupted or not the published version", path=str(path),
                        hint="replace it with the publisher's file (delete it to re-download), "
                             "or pass verify=False to use a modified copy knowingly")
    _VERIFIED[key] = digest
    return path


def default_data_dir() -> Path | None:
    """``BONDGRAPH_DATA`` if set, else ``<project root>/../shared/data`` if it
    exists, else None."""
    env = os.environ.get(ENV_DATA)
    if env:
        return Path(env)
    cand = PROJECT_ROOT.parent / "shared" / "data"
    return cand if cand.is_dir() else None


def cache_dir() -> Path:
    """Download cache: ``BONDGRAPH_CACHE`` or pooch's OS cache for 'bondgraph'."""
    env = os.environ.get(ENV_CACHE)
    if env:
        return Path(env)
    import pooch

    return Path(pooch.os_cache("bondgraph"))


def _dataset(key: str) -> Dataset:
    try:
        return DATASETS[key]
    except KeyError:
        raise DataError(f"unknown data set '{key}' (known: {', '.join(DATASETS)})") from None


def _file(ds: Dataset, name: str) -> DataFile:
    try:
        return ds.files[name]
    except KeyError:
        raise DataError(f"data set '{ds.key}' has no file '{name}' (files: "
                        f"{', '.join(ds.files)})") from None


def find_local(dataset: str, name: str, data_dir: str | Path | None = None) -> Path | None:
    """Path of a data file in a local folder (``<dir>/<folder>/<name>`` or
    ``<dir>/<name>``), or None. ``data_dir`` defaults to
    :func:`default_data_dir`."""
    ds = _dataset(dataset)
    root = Path(data_dir) if data_dir is not None else default_data_dir()
    if root is None:
        return None
    for cand in (root / ds.folder / name, root / name):
        if cand.is_file():
            return cand
    return None


def fetch(dataset: str, name: str, *, cache: str | Path | None = None,
          downloader: Callable | None = None, progressbar: bool = False) -> Path:
    """Fetch one published file with pooch and verify its SHA-256.

    A single file is checked by pooch itself (``known_hash``); a file inside
    an archive is checked after unpacking.

    Parameters
    ----------
    dataset, name : str
        Data set key (:data:`DATASETS`) and file name.
    cache : path, optional
        Download folder (default :func:`cache_dir`).
    downloader : callable, optional
        A pooch downloader ``(url, output_file, pooch)`` (tests use a local
        copy; default: pooch's HTTP downloader).

    Returns
    -------
    Path

    Raises
    ------
    DataError
        If the file is not published (a local conversion), the download
        fails, or a checksum differs (the file is named).
    """
    import pooch

    ds = _dataset(dataset)
    df = _file(ds, name)
    if df.url is None:
        raise DataError(f"'{name}' of data set '{dataset}' is a local conversion, not "
                        f"published; use the publisher's files ({', '.join(f.name for f in ds.files.values() if f.url)})")
    cache = Path(cache) if cache is not None else cache_dir() / ds.folder
    try:
        if df.archive is None:
            got = pooch.retrieve(df.url, known_hash=f"sha256:{df.sha256}", fname=name,
                                 path=cache, downloader=downloader, progressbar=progressbar)
            return verify(got, df.sha256)
        members = pooch.retrieve(df.url, known_hash=None, fname=df.archive, path=cache,
                                 processor=pooch.Unzip(), downloader=downloader,
                                 progressbar=progressbar)
    except DataError:
        raise
    except ValueError as exc:  # pooch's hash mismatch
        raise DataError(f"download of {df.url} failed its checksum: {exc}",
                        path=str(cache / name)) from None
    except Exception as exc:  # network errors of requests, bad zip files, ...
        raise DataError(f"could not fetch {df.url}: {type(exc).__name__}: {exc}",
                        path=str(cache / name),
                        hint=f"download it by hand from {ds.landing} and pass data_dir= or set "
                             f"{ENV_DATA}") from None
    wanted = df.member or name
    hits = [Path(m) for m in members if Path(m).name == wanted]
    if not hits:
        raise DataError(f"archive {df.archive} from {df.url} has no member '{wanted}'",
                        path=str(cache / df.archive))
    return verify(hits[0], df.sha256)


def locate(dataset: str, names: str | tuple[str, ...], data_dir: str | Path | None = None, *,
           verify_checksum: bool = True, download: bool | None = None,
           cache: str | Path | None = None, downloader: Callable | None = None) -> Path:
    """Find (or fetch) a data file and verify it.

    Parameters
    ----------
    dataset : str
    names : str or tuple of str
        File name, or alternatives in order of preference (the first found
        locally wins; the first published one is fetched).
    data_dir : path, optional
        Local folder; given (or ``BONDGRAPH_DATA`` set), a missing file is
        an error unless ``download=True``.
    verify_checksum : bool
    download : bool, optional
        Fetch when not found locally (default: only if no local folder was
        named by ``data_dir`` or ``BONDGRAPH_DATA``).
    cache, downloader
        Passed to :func:`fetch`.

    Raises
    ------
    DataError
        Missing file, checksum mismatch (the file is named), failed download.
    """
    ds = _dataset(dataset)
    names = (names,) if isinstance(names, str) else tuple(names)
    explicit = data_dir is not None or bool(os.environ.get(ENV_DATA))
    root = Path(data_dir) if data_dir is not None else default_data_dir()
    if data_dir is not None and not Path(data_dir).is_dir():
        raise DataError("data folder does not exist", path=str(data_dir))
    for nm in names:
        p = find_local(dataset, nm, root) if root is not None else None
        if p is not None:
            return verify(p, _file(ds, nm).sha256) if verify_checksum else p
    if download is None:
        download = not explicit
    if not download:
        raise DataError(f"data set '{dataset}': none of {', '.join(names)} in {root} "
                        f"(looked in {root}/{ds.folder}/ and {root}/)",
                        path=str(root), hint=f"get the files from {ds.landing}, or call with "
                                             f"download=True")
    published = [nm for nm in names if _file(ds, nm).url is not None]
    if not published:
        raise DataError(f"data set '{dataset}': {', '.join(names)} not found locally and not "
                        f"downloadable")
    return fetch(dataset, published[0], cache=cache, downloader=downloader)


# ---------------------------------------------------------------------- EMPS
def emps(which: str = "estimation", data_dir: str | Path | None = None, *, verify: bool = True,
         download: bool | None = None, cache=None, downloader=None) -> Experiment:
    """EMPS record (Janot, Gautier & Brunot 2019): 24 841 samples at 1 kHz.

    Reads the publisher's ``DATA_EMPS.mat`` / ``DATA_EMPS_PULSES.mat``
    (falls back to the project's CSV conversions ``emps_estimation.csv`` /
    ``emps_validation_pulses.csv`` if only those are present).

    Parameters
    ----------
    which : {"estimation", "validation"}
        ``DATA_EMPS`` (training) or ``DATA_EMPS_PULSES`` (test: 25 force
        pulses of 5 V, 500 ms, one per second from t = 0.344 s).
    data_dir, verify, download, cache, downloader
        See :func:`locate`.

    Returns
    -------
    Experiment
        Columns ``qm [m]`` (output: motor position, load side), ``qg [m]``
        (reference position, input), ``vir [V]`` (drive command, input),
        ``tau [N]`` = gtau·vir (motor force, input) and, for the validation
        record, ``pulses_N [1]`` (pulse marker). ``meta["constants"]`` holds
        gtau [N/V], kp [1/s], kv [V/(m/s)]; ``meta["split"]`` the official
        benchmark use (train: estimation; test: validation, first 20
        samples for state initialisation).
    """
    which = {"train": "estimation", "test": "validation"}.get(which, which)
    if which not in ("estimation", "validation"):
        raise DataError(f"EMPS record '{which}' unknown: use 'estimation' or 'validation'")
    mat, csvname = (("DATA_EMPS.mat", "emps_estimation.csv") if which == "estimation" else
                    ("DATA_EMPS_PULSES.mat", "emps_validation_pulses.csv"))
    path = locate("emps", (mat, csvname), data_dir, verify_checksum=verify, download=download,
                  cache=cache, downloader=downloader)
    consts = dict(EMPS_CONSTANTS)
    if path.suffix.lower() == ".mat":
        m = loadmat(path)
        cols = {k: np.asarray(m[k], dtype=float).reshape(-1)
                for k in ("t", "qm", "qg", "vir", "pulses_N") if k in m}
        for k in consts:
            if k in m:
                consts[k] = float(np.asarray(m[k]).reshape(-1)[0])
    else:
        header, arr = read_table(path)
        cols = {h: arr[:, j] for j, h in enumerate(header)}
    t = cols.pop("t")
    columns = {"qm": cols["qm"], "qg": cols["qg"], "vir": cols["vir"],
               "tau": consts["gtau"] * cols["vir"]}
    units = {"qm": "m", "qg": "m", "vir": "V", "tau": "N"}
    roles = {"qm": "output", "qg": "input", "vir": "input", "tau": "input"}
    if "pulses_N" in cols:
        columns["pulses_N"] = cols["pulses_N"]
        units["pulses_N"] = "1"
        roles["pulses_N"] = "other"
    df = DATASETS["emps"].files[path.name]
    meta = {
        "name": f"emps_{which}",
        "description": ("EMPS " + ("estimation record (DATA_EMPS)" if which == "estimation"
                                   else "validation record with force pulses (DATA_EMPS_PULSES)")
                        + ": DC motor, ball screw and load under a PD position loop, 1 kHz. "
                          "tau = gtau*vir is the motor force on the load side."),
        "dt": 0.001,
        "constants": consts,
        "split": {"role": "train" if which == "estimation" else "test",
                  "input": "vir", "output": "qm", "test_init_samples": 20},
        "source": _source("emps", path, df),
    }
    return Experiment.from_arrays(t, columns, units=units, roles=roles, meta=meta,
                                  check_gaps=True)


def _source(key: str, path: Path, df: DataFile) -> dict:
    ds = DATASETS[key]
    return {"file": str(path), "sha256": df.sha256, "url": df.url, "landing": ds.landing,
            "citation": ds.citation}


# ----------------------------------------------------------------------- CED
def ced(run: str = "prbs_1", data_dir: str | Path | None = None, *, verify: bool = True,
        download: bool | None = None, cache=None, downloader=None) -> Experiment:
    """One CED run (Wigren & Schoukens 2017): 500 samples, Ts = 0.02 s.

    Parameters
    ----------
    run : str
        ``prbs_1`` (u1/z1, amplitude 1 V), ``prbs_2`` (1.5 V), ``prbs_3``
        (0.5 V), ``unif_11``, ``unif_12`` (uniform random amplitudes); the
        column names ``u1``, ``z12``, ... are accepted too.
    data_dir, verify, download, cache, downloader
        See :func:`locate`.

    Returns
    -------
    Experiment
        Columns ``u [V]`` (sum of the motor voltages, input) and ``z``
        (rectified pulley speed, output; the report gives no unit), ``t = k
        Ts``. For the ``unif`` runs ``meta["split"]`` holds the official
        benchmark split (train [0, 400), test [400, 500)).

    Notes
    -----
    Reads the publisher's CSV (each line ends with a comma); falls back to
    the ``.MAT`` file if only that is present.
    """
    key = _ced_key(run)
    fname, ucol, zcol, desc = CED_RUNS[key]
    path = locate("ced", (f"{fname}.csv", f"{fname}.MAT"), data_dir, verify_checksum=verify,
                  download=download, cache=cache, downloader=downloader)
    if path.suffix.lower() == ".csv":
        header, arr = read_table(path)
        header = [h.strip('"') for h in header]
        data = {h: arr[:, j] for j, h in enumerate(header)}
    else:
        m = loadmat(path)
        data = {k: np.asarray(v, dtype=float).reshape(-1) for k, v in m.items()
                if not k.startswith("__")}
    for c in (ucol, zcol):
        if c not in data:
            raise DataError(f"CED file lacks column '{c}'", path=str(path), column=c)
    u, z = data[ucol], data[zcol]
    t = np.arange(u.size) * CED_TS
    meta = {
        "name": f"ced_{key}",
        "description": f"CED run {ucol}/{zcol}: {desc}. Input u = sum of the two motor "
                       f"voltages; output z = pulley speed from a sign-blind pulse counter "
                       f"(|speed|) after a ~12 Hz anti-aliasing filter.",
        "dt": CED_TS,
        "columns_in_file": {"u": ucol, "z": zcol},
        "source": _source("ced", path, DATASETS["ced"].files[path.name]),
    }
    if key.startswith("unif"):
        meta["split"] = {"train": [0, 400], "test": [400, 500], "test_init_samples": 10}
    return Experiment.from_arrays(t, {"u": u, "z": z}, units={"u": "V", "z": None},
                                  roles={"u": "input", "z": "output"}, meta=meta,
                                  check_gaps=True)


def _ced_key(run: str) -> str:
    run = str(run)
    if run in CED_RUNS:
        return run
    for key, (_, ucol, zcol, _) in CED_RUNS.items():
        if run in (ucol, zcol, ucol[1:]):
            return key
    raise DataError(f"unknown CED run '{run}' (runs: {', '.join(CED_RUNS)})")


def ced_runs(data_dir: str | Path | None = None, *, verify: bool = True,
             download: bool | None = None, cache=None, downloader=None) -> dict[str, Experiment]:
    """All five CED runs by name (see :func:`ced` for the options)."""
    return {k: ced(k, data_dir, verify=verify, download=download, cache=cache,
                   downloader=downloader) for k in CED_RUNS}


# ------------------------------------------------------------------ Silverbox
def silverbox(part: str = "train", data_dir: str | Path | None = None, *, verify: bool = True,
              download: bool | None = None, cache=None, downloader=None) -> Experiment:
    """One part of the Silverbox record SNLS80mV (Wigren & Schoukens 2013): an
    electronic Duffing oscillator, input V1 [V] (the "force"), output V2 [V]
    (the "displacement"), Ts = 2^14 / 10^7 s.

    Parameters
    ----------
    part : str
        A key of :data:`SILVERBOX_PARTS`: ``train`` (the official train +
        validation block), ``test_multisine``, ``test_arrow``,
        ``test_arrow_noextrap`` or ``full``.
    data_dir, verify, download, cache, downloader
        See :func:`locate`.

    Returns
    -------
    Experiment
        Columns ``V1 [V]`` (input) and ``V2 [V]`` (output) of the samples of
        ``part``, ``t = k Ts`` with k the sample index in the whole record (so
        parts keep their place in time). ``meta["split"]`` gives the range,
        and for test parts ``meta["init_samples"]`` = 50: the published
        protocol may use them to initialise the state and scores the
        simulation RMS error [mV] on the rest.

    Raises
    ------
    DataError
        Unknown part, missing columns, or a file that fails its checksum.

    Notes
    -----
    Reads the ``.mat`` file (full precision) with scipy, else the CSV (5
    significant digits). The raw voltages carry offsets of a few mV (the
    upstream README removes the means); they are left in the record.
    """
    if part not in SILVERBOX_PARTS:
        raise DataError(f"unknown Silverbox part '{part}' (parts: {', '.join(SILVERBOX_PARTS)})")
    i0, i1, desc = SILVERBOX_PARTS[part]
    path = locate("silverbox", ("SNLS80mV.mat", "SNLS80mV.csv"), data_dir,
                  verify_checksum=verify, download=download, cache=cache,
                  downloader=downloader)
    if path.suffix.lower() == ".mat":
        m = loadmat(path)
        data = {k: np.asarray(v, dtype=float).reshape(-1) for k, v in m.items()
                if not k.startswith("__")}
    else:
        header, arr = read_table(path)
        data = {h.strip('"'): arr[:, j] for j, h in enumerate(header) if h.strip('"')}
    for c in ("V1", "V2"):
        if c not in data:
            raise DataError(f"Silverbox file lacks column '{c}'", path=str(path), column=c)
    k = np.arange(i0, i1)
    meta = {
        "name": f"silverbox_{part}",
        "description": f"Silverbox SNLS80mV samples [{i0}, {i1}): {desc}. V1: input voltage "
                       f"(force), V2: output voltage (displacement).",
        "dt": SILVERBOX_TS,
        "split": [i0, i1],
        "source": _source("silverbox", path, DATASETS["silverbox"].files[path.name]),
    }
    if part.startswith("test"):
        meta["init_samples"] = SILVERBOX_INIT_SAMPLES
    return Experiment.from_arrays(k * SILVERBOX_TS, {"V1": data["V1"][k], "V2": data["V2"][k]},
                                  units={"V1": "V", "V2": "V"},
                                  roles={"V1": "input", "V2": "output"}, meta=meta)


# ------------------------------------------------------------- Camry, EPA
def camry_dyno(test: str | int = "61811012", data_dir: str | Path | None = None, *,
               verify: bool = True, download: bool | None = None, cache=None,
               downloader=None):
    """One ANL D3 2018 Camry chassis-dyno test (1 Hz) as a pandas DataFrame.

    Parameters
    ----------
    test : str or int
        ``"61811011"`` .. ``"61811014"`` (or 11 .. 14); see
        :data:`CAMRY_TESTS`.

    Returns
    -------
    pandas.DataFrame
        The file's columns ``Time[s]``, ``Eng_FuelFlow_Direct_DI[ccps]``
        (cm³/s), ``Dyno_Spd[mph]``, plus ``v [m/s]`` (speed in SI).
        ``df.attrs`` holds ``units``, ``cycle`` and ``source``.
    """
    import pandas as pd

    tid = str(test)
    if len(tid) <= 2:
        tid = f"618110{int(tid):02d}"
    if tid not in CAMRY_TESTS:
        raise DataError(f"unknown Camry test '{test}' (tests: {', '.join(CAMRY_TESTS)})")
    path = locate("camry", f"{tid}.csv", data_dir, verify_checksum=verify, download=download,
                  cache=cache, downloader=downloader)
    df = pd.read_csv(path)
    df["v [m/s]"] = df["Dyno_Spd[mph]"] * 0.44704
    df.attrs.update({
        "test": tid, "cycle": CAMRY_TESTS[tid],
        "units": {"Time[s]": "s", "Eng_FuelFlow_Direct_DI[ccps]": "cm^3/s",
                  "Dyno_Spd[mph]": "mph", "v [m/s]": "m/s"},
        "source": _source("camry", path, DATASETS["camry"].files[path.name]),
    })
    return df


def epa_test_cars(data_dir: str | Path | None = None, *, verify: bool = True,
                  download: bool | None = None, cache=None, downloader=None):
    """The EPA MY2022 Test Car List (4397 certification tests) as a DataFrame.

    Returns
    -------
    pandas.DataFrame
        The file's 67 columns (read with ``encoding="utf-8-sig"``); use
        :func:`road_load_si` for A, B, C in SI units.
    """
    import pandas as pd

    path = locate("epa", "22-tstcar.csv", data_dir, verify_checksum=verify, download=download,
                  cache=cache, downloader=downloader)
    df = pd.read_csv(path, encoding="utf-8-sig", low_memory=False)
    df.attrs["source"] = _source("epa", path, DATASETS["epa"].files[path.name])
    return df


def road_load_si(df):
    """Add SI road-load columns to an EPA table (copy returned).

    ``A_target [N]``, ``B_target [N/(m/s)]``, ``C_target [N/(m/s)^2]`` and
    the same for ``Set``, from the lbf/mph columns (F = A + B v + C v²),
    converted with pint: 1 lbf = 4.44822 N, 1 mph = 0.44704 m/s, so B x
    9.9503 and C x 22.258.
    """
    from bondgraph.core.units import factor

    out = df.copy()
    fa = factor("lbf", "N")
    fb = factor("lbf/mph", "N/(m/s)")
    fc = factor("lbf/mph^2", "N/(m/s)^2")
    for kind in ("Target", "Set"):
        out[f"A_{kind.lower()} [N]"] = df[f"{kind} Coef A (lbf)"] * fa
        out[f"B_{kind.lower()} [N/(m/s)]"] = df[f"{kind} Coef B (lbf/mph)"] * fb
        out[f"C_{kind.lower()} [N/(m/s)^2]"] = df[f"{kind} Coef C (lbf/mph**2)"] * fc
    return out


__all__ = ["DATASETS", "DataFile", "Dataset", "EMPS_CONSTANTS", "CED_TS", "CED_RUNS",
           "SILVERBOX_TS", "SILVERBOX_PARTS", "SILVERBOX_INIT_SAMPLES", "SILVERBOX_PUBLISHED_MV",
           "silverbox",
           "CAMRY_TESTS", "emps", "ced", "ced_runs", "camry_dyno", "epa_test_cars",
           "road_load_si", "locate", "fetch", "verify", "sha256", "default_data_dir",
           "find_local", "cache_dir"]
