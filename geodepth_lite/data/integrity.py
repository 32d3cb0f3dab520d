"""A synthetic dataset's integrity: its checksums, ``verify`` and the checks run before it is used.

``synth.py`` writes ``DIR/checksums.sha256`` last (``sha256sum -c`` format, one line per file
of ``dataset_files``), so its presence marks a finished dataset. ``verify`` names every file
that is missing, changed or unreadable against it (or, without it, how many frames of each
split are on disk); ``check_dataset`` turns those problems into one error line before
``train`` or ``evaluate`` use a dataset (``--no-verify`` skips it); ``is_complete`` is the
cheap check (no hashing) of ``synth.ensure_dataset``.

Which renderer made a dataset: ``DIR/renderer.json`` (``renderer_of``), written by every renderer
but VTK and listed in checksums.sha256 after manifest.json; a dataset without it (every dataset
made before there was a second renderer) was made by VTK. The same manifest gives the same bytes
per renderer only (docs/dataset.md says where each promise holds).

Command: ``python -m geodepth_lite verify DIR``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from geodepth_lite.core.errors import UserError
from geodepth_lite.data.bounds import MAX_DATASET_FILE_BYTES, MAX_MANIFEST_BYTES, dataset_file, inside_folder
from geodepth_lite.utils import FileProblem, os_reason, write_bytes_atomic

MAX_SPLIT_FRAMES = 10_000_000  # frames of one split, at most (as manifest's check of 'splits')
MAX_CHECKSUMS_BYTES = 2**30  # checksums.sha256, at most
RENDERER_FILE = "renderer.json"  # which renderer made the dataset; absent: VTK
VTK_RECORD = {"renderer": "vtk"}  # the record of a dataset without RENDERER_FILE


def dataset_files(m: dict) -> list[str]:
    """Every file of a dataset of manifest ``m``, relative to its directory, in checksums.sha256's order."""
    files = ["manifest.json"]
    for split, n in m["splits"].items():
        files.append(f"{split}/frames.jsonl")
        files += [f"{split}/rgb/{i:06d}.png" for i in range(n)] + [f"{split}/depth/{i:06d}.npy" for i in range(n)]
    return files


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file, read in 1 MiB chunks (hex digest)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def checksum_files(out: Path, m: dict) -> list[str]:
    """The files checksums.sha256 lists: ``dataset_files(m)``, with RENDERER_FILE after manifest.json when there."""
    files = dataset_files(m)
    return files[:1] + [RENDERER_FILE] + files[1:] if (Path(out) / RENDERER_FILE).is_file() else files


def renderer_of(root: str | Path) -> dict:
    """The renderer record of a dataset directory: RENDERER_FILE's object, or VTK_RECORD without it (raises
    FileProblem when it is there but unreadable or not a JSON object with a "renderer" string)."""
    path = Path(root) / RENDERER_FILE
    if not path.exists():
        return dict(VTK_RECORD)
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError) as exc:  # ValueError: json.JSONDecodeError, UnicodeDecodeError
        raise FileProblem(f"cannot read {path}: {os_reason(exc) if isinstance(exc, OSError) else exc}", path) from exc
    if not isinstance(rec, dict) or not isinstance(rec.get("renderer"), str):
        raise FileProblem(f"cannot read {path}: not a JSON object with a \"renderer\" string", path)
    return rec


def write_checksums(out: Path, m: dict) -> None:
    """Write ``out/checksums.sha256`` over ``checksum_files``; synth writes it last, to mark completion."""
    lines = []
    for rel in checksum_files(out, m):
        try:
            lines.append(f"{file_sha256(out / rel)}  {rel}\n")
        except OSError as exc:
            raise FileProblem(f"cannot read {out / rel}: {os_reason(exc)}", out / rel) from exc
    write_bytes_atomic(out / "checksums.sha256", "".join(lines).encode())


def frame_counts(root: str | Path, m: dict) -> dict[str, tuple[int, int]]:
    """Per split of manifest ``m``: (complete frames in dataset directory ``root``, frames expected).

    A frame is complete when both its files are there (``<split>/rgb/NNNNNN.png`` and
    ``<split>/depth/NNNNNN.npy``; each is written atomically, so a present file is whole).
    """
    root = Path(root)
    out = {}
    for split, n in m["splits"].items():
        numbers = {}
        for kind, ext in (("rgb", ".png"), ("depth", ".npy")):
            try:  # the files there, not every number up to n: a manifest may claim far more frames
                numbers[kind] = {int(p.name[:6]) for p in (root / split / kind).iterdir()
                                 if len(p.name) == 10 and p.name.endswith(ext) and p.name[:6].isdigit()}
            except OSError:  # not there yet (or unreadable: counted as absent)
                numbers[kind] = set()
        out[split] = (sum(1 for i in numbers["rgb"] & numbers["depth"] if i < n), n)
    return out


def _dataset_manifest(root: Path) -> tuple[dict | None, str | None]:
    """(DIR/manifest.json with a usable "splits", None), or (None, the problem line saying what is wrong)."""
    mpath = root / "manifest.json"
    if not mpath.exists():
        return None, ("missing: manifest.json and checksums.sha256 (not a dataset written by synth, or synth "
                      "stopped before it began: run synth again)")
    try:
        if mpath.stat().st_size > MAX_MANIFEST_BYTES:
            raise UserError(f"over the limit of {MAX_MANIFEST_BYTES} bytes for a manifest")
        m = json.loads(mpath.read_text())
    except OSError as exc:
        reason = os_reason(exc)
    except RecursionError:
        reason = "its JSON is nested too deep"
    except ValueError as exc:  # json.JSONDecodeError, UnicodeDecodeError
        reason = f"not valid JSON: {exc}" if isinstance(exc, json.JSONDecodeError) else str(exc)
    else:
        splits = m.get("splits") if isinstance(m, dict) else None
        ok = (isinstance(splits, dict) and splits
              and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in splits.values()))
        too_many = ok and max(splits.values()) > MAX_SPLIT_FRAMES
        if ok and not too_many:
            return m, None
        reason = (f"'splits' claims {max(splits.values())} frames in one split, over the limit of "
                  f"{MAX_SPLIT_FRAMES}" if too_many else "no 'splits' object of frame counts")
    return None, (f"unreadable: manifest.json ({reason}); checksums.sha256 is missing too, so the frames cannot "
                  "be counted: run synth again with --overwrite")


def _incomplete(root: Path) -> list[str]:
    """verify's report on a dataset directory without checksums.sha256: frames present and expected per split."""
    m, problem = _dataset_manifest(root)
    if m is None:
        return [problem]
    counts = frame_counts(root, m)
    parts = [f"{split} {have}/{n}" for split, (have, n) in counts.items()]
    parts[0] += " frames"
    return [f"incomplete: {', '.join(parts)} (checksums.sha256 is written last; run synth again to finish)"]


def verify(root: str | Path) -> list[str]:
    """Problems of a dataset directory against its checksums: 'missing: f', 'changed: f', 'unreadable: f'.

    An empty list means every listed file is present and unchanged. Without checksums.sha256
    (synth has not finished) the one problem is 'incomplete: ...' with the frames present and
    expected per split of manifest.json (or what is wrong with manifest.json).
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"dataset directory {root} does not exist")
    if not root.is_dir():
        raise FileProblem(f"cannot verify {root}: it is a file, not a dataset folder", root)
    sums = root / "checksums.sha256"
    if not sums.is_file():
        return _incomplete(root)
    try:
        if sums.stat().st_size > MAX_CHECKSUMS_BYTES:
            return [f"unreadable: checksums.sha256 (over the limit of {MAX_CHECKSUMS_BYTES} bytes)"]
        text = sums.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        return [f"unreadable: checksums.sha256 ({os_reason(exc) if isinstance(exc, OSError) else 'not a text file'})"]
    problems = []
    for line_no, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        digest, _, rel = line.partition("  ")
        if len(digest) != 64 or not rel:
            problems.append(f"unreadable: checksums.sha256 line {line_no}")
            continue
        path = root / rel
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            problems.append(f"outside: {rel} (checksums.sha256 line {line_no} names a file outside the dataset "
                            "folder; never read)")
            continue
        if not path.exists() and not path.is_symlink():
            problems.append(f"missing: {rel}")
            continue
        if inside_folder(root, rel) is None:
            problems.append(f"outside: {rel} (checksums.sha256 line {line_no} names a link leading outside the "
                            "dataset folder, or something other than a regular file; never read)"
                            if path.is_symlink() or not path.resolve().is_relative_to(root.resolve())
                            else f"unreadable: {rel} (not a regular file; never read)")
            continue
        size = path.stat().st_size
        if size > MAX_DATASET_FILE_BYTES:
            problems.append(f"unreadable: {rel} ({size} bytes, over the limit of {MAX_DATASET_FILE_BYTES} bytes "
                            "for one file of a dataset)")
            continue
        try:
            actual = file_sha256(path)
        except OSError as exc:
            problems.append(f"unreadable: {rel} ({os_reason(exc)})")
            continue
        if actual != digest:
            problems.append(f"changed: {rel}")
    if (root / RENDERER_FILE).exists() and not any(ln.endswith(f"  {RENDERER_FILE}") for ln in text.splitlines()):
        problems.append(f"changed: {RENDERER_FILE} (not listed in checksums.sha256: the frames were made by VTK, "
                        "the file says otherwise)")
    return problems + _record_problems(root, text, problems)


def _record_problems(root: Path, text: str, problems: list[str]) -> list[str]:
    """Each unchanged ``<split>/frames.jsonl`` read as ``train`` and ``evaluate`` read it
    (:func:`read_frames`: every record's files inside the folder, regular, listed in
    checksums.sha256); 'unreadable: <split>/frames.jsonl (why)' for the first record refused in a split.
    A split with a problem already (a missing or changed file) is left to those lines."""
    flagged = {Path(p.partition(": ")[2].split(" ", 1)[0]).parts[0] for p in problems if ": " in p}
    found = []
    for line in text.splitlines():
        rel = line.partition("  ")[2]
        parts = Path(rel).parts
        if len(parts) != 2 or parts[1] != "frames.jsonl" or parts[0] in flagged or Path(rel).is_absolute():
            continue
        try:
            read_frames(root, parts[0])
        except (OSError, ValueError) as exc:
            found.append(f"unreadable: {rel} ({' '.join(str(exc).split())[:300]})")
    return found


def _complete_splits(root: Path, splits) -> bool:
    """Without checksums.sha256: whether every frame of ``splits`` (those in manifest.json) and
    their frames.jsonl are on disk."""
    m, _ = _dataset_manifest(root)
    if m is None:
        return False
    counts = frame_counts(root, {"splits": {s: n for s, n in m["splits"].items() if s in splits}})
    return all(have == n and (root / s / "frames.jsonl").is_file() for s, (have, n) in counts.items())


def check_dataset(root: str | Path, splits=None, *, limit: int = 5) -> None:
    """Check a synthetic dataset directory against its checksums.sha256 before it is used
    (``train`` and ``evaluate`` call this unless ``--no-verify``).

    splits: check only the files of these splits (and the top-level ones, manifest.json);
    None: all. Without checksums.sha256 (synth did not finish, or a folder put together by
    hand) there is nothing to compare with: the check passes only when ``splits`` (not None)
    are complete on disk. Raises a one-line ValueError naming the problems (the first
    ``limit``, then "and N more") and how to fix them: synth renders missing or changed frames again.
    """
    root = Path(root)
    problems = verify(root)
    if splits is not None:
        if not (root / "checksums.sha256").is_file():
            problems = [] if _complete_splits(root, set(splits)) else problems
        else:
            def split_of(problem: str) -> str | None:
                rel = problem.partition(": ")[2]
                return rel.split("/", 1)[0] if "/" in rel.split(" ", 1)[0] else None
            problems = [p for p in problems if split_of(p) in (None, *splits)]
    if not problems:
        return
    shown = "; ".join(problems[:limit])
    if len(problems) > limit:
        shown += f"; and {len(problems) - limit} more"
    cmd = f"python -m geodepth_lite synth --manifest {root / 'manifest.json'} --out {root}"
    raise UserError(f"dataset {root} failed verification against checksums.sha256: {shown}. "
                     f"Regenerate it with `{cmd}` (renders missing and changed frames again), "
                     "or pass --no-verify to use it as it is")


def is_complete(root: Path, m: dict) -> bool:
    """Cheap completeness check: same manifest, checksums written, every file present (no hashing)."""
    try:
        if json.loads((root / "manifest.json").read_text()) != m:
            return False
    except (OSError, json.JSONDecodeError):
        return False
    return (root / "checksums.sha256").is_file() and all((root / f).is_file() for f in dataset_files(m))


def is_complete_by(root: Path, m: dict, renderer: str | None) -> bool:
    """``is_complete``, and made by ``renderer`` ("vtk", "torch"; None: any)."""
    if not is_complete(root, m):
        return False
    try:
        return renderer is None or renderer_of(root)["renderer"] == renderer
    except FileProblem:
        return False


# ----------------------------------------------------------------------------- CLI


def add_arguments_verify(parser) -> None:
    parser.add_argument("dir", help="dataset directory (holds manifest.json and checksums.sha256)")


def run_verify(args) -> int:
    problems = verify(args.dir)
    for p in problems:
        print(p)
    if problems:
        print(f"verify: {len(problems)} problem(s) in {args.dir}")
        return 1
    n = sum(1 for line in (Path(args.dir) / "checksums.sha256").read_text().splitlines() if line.strip())
    rec = renderer_of(args.dir)
    made = "" if rec == VTK_RECORD else f" (made by the {rec['renderer']} renderer on {rec.get('device', '?')})"
    print(f"verify: ok, {n} files match checksums.sha256{made}")
    return 0


# --------------------------------------------------------------------------- frames.jsonl


def read_frames(root: str | Path, split: str) -> list[dict]:
    """The frames.jsonl records of a split (clear errors for a missing directory or split)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset directory {root} does not exist "
                                "(generate it with synth.ensure_dataset or `python -m geodepth_lite synth`)")
    path = root / split / "frames.jsonl"
    if not path.is_file():
        have = sorted(p.name for p in root.iterdir() if (p / "frames.jsonl").is_file())
        raise FileNotFoundError(f"dataset {root} has no split {split!r} (splits present: {', '.join(have) or 'none'}); "
                                "an unfinished dataset is completed by running synth again")
    size = path.stat().st_size
    if size > MAX_DATASET_FILE_BYTES:
        raise FileProblem(f"cannot read {path}: {size} bytes, over the limit of {MAX_DATASET_FILE_BYTES} bytes "
                          "for one file of a dataset", path)
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise FileProblem(f"cannot read {path}: not a text file", path) from exc
    covered = _checksummed(root)
    records = []
    for line_no, line in enumerate(text.splitlines(), 1):
        if line.strip():
            records.append(_frame_record(root, path, line_no, line, covered))
    return records


RECORD_TEXT_KEYS = ("rgb", "depth", "organ", "group")  # what every frames.jsonl record holds, with "K" and "index"


def _checksummed(root: Path) -> set[str] | None:
    """The file names checksums.sha256 lists (None when the dataset has none: synth did not finish,
    and ``integrity.check_dataset`` decides whether it may be used)."""
    sums = root / "checksums.sha256"
    if not sums.is_file():
        return None
    try:
        if sums.stat().st_size > MAX_DATASET_FILE_BYTES:
            raise FileProblem(f"cannot read {sums}: over the limit of {MAX_DATASET_FILE_BYTES} bytes", sums)
        return {line.partition("  ")[2] for line in sums.read_text().splitlines() if "  " in line}
    except (OSError, UnicodeDecodeError) as exc:
        raise FileProblem(f"cannot read {sums}: {os_reason(exc) if isinstance(exc, OSError) else 'not a text file'}",
                          sums) from exc


def _frame_record(root: Path, path: Path, line_no: int, line: str, covered: set[str] | None) -> dict:
    """One frames.jsonl record, checked: its keys and types, K a finite 3x3, and its files regular
    files inside the dataset folder, listed in checksums.sha256. A FileProblem naming the file and line."""
    where = f"{path} line {line_no}"
    try:
        rec = json.loads(line)
    except RecursionError:
        raise FileProblem(f"cannot read {where}: its JSON is nested too deep", path) from None
    except ValueError as exc:
        raise FileProblem(f"cannot read {where}: not valid JSON ({exc})", path) from None
    if not isinstance(rec, dict):
        raise FileProblem(f"cannot read {where}: a frame record must be a JSON object", path)
    missing = [k for k in (*RECORD_TEXT_KEYS, "K", "index") if k not in rec]
    if missing:
        raise FileProblem(f"cannot read {where}: the frame record lacks {', '.join(repr(k) for k in missing)}", path)
    bad = [k for k in RECORD_TEXT_KEYS if not isinstance(rec[k], str)]
    if bad:
        raise FileProblem(f"cannot read {where}: {bad[0]!r} must be a string, got {str(rec[bad[0]])[:60]}", path)
    if not isinstance(rec["index"], int) or isinstance(rec["index"], bool) or not 0 <= rec["index"] < 2**63:
        raise FileProblem(f"cannot read {where}: 'index' must be an integer from 0 to 2^63 - 1, got "
                          f"{str(rec['index'])[:60]}", path)
    try:
        K = np.asarray(rec["K"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # not numbers, ragged, or an integer of hundreds of digits
        K = None
    with np.errstate(over="ignore"):  # the loaders hand K on as float32: it must stay finite there
        finite = K is not None and K.shape == (3, 3) and np.isfinite(K.astype(np.float32)).all()
    if not finite or not (K[0, 0] > 0 and K[1, 1] > 0) or K[2].tolist() != [0.0, 0.0, 1.0]:
        raise FileProblem(f"cannot read {where}: 'K' must be a pinhole camera's 3x3 matrix of finite numbers "
                          f"(focal lengths positive, last row 0 0 1), got {str(rec['K'])[:60]}", path)
    for key in ("rgb", "depth"):
        dataset_file(root, rec[key], key, where)  # confined, regular, bounded
        if covered is not None and str(Path(rec[key])) not in covered and rec[key] not in covered:
            raise FileProblem(f"cannot use {where}: its {key} file {rec[key]} is not listed in "
                              f"{root / 'checksums.sha256'}, so it cannot be verified", path)
    return rec
