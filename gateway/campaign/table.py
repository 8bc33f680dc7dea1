"""A campaign's results: one table, a row per point, in DIR.

While a campaign runs, every finished batch is appended as a Parquet part file
(``DIR/parts/part-<session>-<n>.parquet``, written under a temporary name and renamed:
a part is there whole or not at all). At the end, and at the start of a re-run, the parts
are compacted with the table into ``DIR/results.parquet`` (again through a rename), and
then removed. A row's ``hash`` names its point's configuration: reading the table keeps
the last row of each hash, so a crash between the rename and the removal of the parts
repeats no point and loses none. ``--csv`` writes ``DIR/results.csv`` beside it.

Columns: ``point`` (its number in the campaign), ``hash``, one per axis (its value; a
settings table by its label), ``status``, ``stop``, ``stop_reason``, ``exit_status``, the
metrics (:mod:`gateway.campaign.metrics`), ``wall_time_s``, ``worker``, ``run_dir``,
``session`` (which invocation ran it), and what reproduces the point alone: ``command``,
``options``, ``plant_toml``, ``controller_params_toml``. The campaign itself (its file's
text, axes, criteria) is in the Parquet file's metadata and in ``DIR/campaign.json``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from gateway.campaign.metrics import is_metric, window_sort_key
from gateway.errors import UserError

RESULTS = "results.parquet"
PARTS = "parts"
CSV = "results.csv"
META = "campaign.json"
META_KEY = b"can_drive_hil.campaign"

FRONT = ("point", "hash")
OUTCOME = ("status", "stop", "stop_reason", "exit_status")
TAIL = ("wall_time_s", "worker", "run_dir", "session", "command", "options", "plant_toml",
        "controller_params_toml")
_TYPES = {"point": "int64", "hash": "string", "status": "string", "stop": "string",
          "stop_reason": "string", "exit_status": "int64", "wall_time_s": "float64",
          "worker": "string", "run_dir": "string", "session": "string", "command": "string",
          "options": "string", "plant_toml": "string", "controller_params_toml": "string"}


def arrow() -> tuple[Any, Any]:
    """pyarrow and pyarrow.parquet, or a UserError saying how to install them."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise UserError("a campaign's table is Parquet and needs pyarrow, which is not "
                        "installed: pip install 'can-drive-hil[campaign]' (scripts/bootstrap "
                        "installs it)") from exc
    return pa, pq


def _replace(tmp: Path, path: Path) -> Path:
    os.replace(tmp, path)
    return path


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def _type(pa: Any, name: str, params: Mapping[str, str]) -> Any:
    kind = params.get(name) or _TYPES.get(name) or ("float64" if is_metric(name) else "string")
    return {"float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_(),
            "string": pa.string()}[kind]


def column_order(names: Sequence[str], params: Sequence[str]) -> list[str]:
    """The table's columns in order: point and hash, the axes, the outcome, the metrics,
    the rest."""
    present = set(names)
    metrics = sorted((n for n in names if is_metric(n) and n not in _TYPES), key=window_sort_key)
    known = {*FRONT, *params, *OUTCOME, *metrics, *TAIL}
    rest = [n for n in names if n not in known]
    return [n for n in (*FRONT, *params, *OUTCOME, *metrics, *TAIL, *rest) if n in present]


def to_table(rows: Sequence[Mapping[str, Any]], params: Mapping[str, str]) -> Any:
    """Rows (name → value) as an Arrow table with the table's column types: an axis's by
    ``params`` (name → float64, int64, bool or string), metrics float64."""
    pa, _ = arrow()
    names = list(dict.fromkeys(k for r in rows for k in r))
    cols, fields = [], []
    for name in column_order(names, list(params)):
        typ = _type(pa, name, params)
        values = [r.get(name) for r in rows]
        if typ == pa.string():
            values = [None if v is None else str(v) for v in values]
        elif typ == pa.float64():
            values = [None if v is None else float(v) for v in values]
        cols.append(pa.array(values, type=typ))
        fields.append(pa.field(name, typ))
    return pa.Table.from_arrays(cols, schema=pa.schema(fields))


def _concat(tables: list[Any], params: Sequence[str]) -> Any:
    """Tables with possibly different columns as one, then the last row of each hash."""
    pa, _ = arrow()
    table = pa.concat_tables(tables, promote_options="permissive")
    last = {h: i for i, h in enumerate(table.column("hash").to_pylist())}
    table = table.take(sorted(last.values()))
    order = column_order(table.column_names, params)
    return table.select(order)


class ResultTable:
    """The results table of a campaign in ``dir``: ``meta`` (JSON-able: the campaign),
    ``params`` (each axis's column type)."""

    def __init__(self, dir: Path, meta: Mapping[str, Any], params: Mapping[str, str]) -> None:
        self.dir = dir
        self.parts = dir / PARTS
        self.meta = dict(meta)
        self.params = dict(params)
        self.session = f"{datetime.now():%Y%m%d-%H%M%S}-{os.getpid()}"
        self._seq = 0

    @property
    def path(self) -> Path:
        return self.dir / RESULTS

    def clean(self) -> None:
        """Temporary files a killed campaign left (never a part or the table)."""
        for d in (self.dir, self.parts):
            if d.is_dir():
                for p in d.glob(".*.tmp-*"):
                    p.unlink(missing_ok=True)

    def _part_files(self) -> list[Path]:
        return sorted(self.parts.glob("part-*.parquet")) if self.parts.is_dir() else []

    def read(self) -> Any | None:
        """The table and its parts as one (the last row of each point), or None if empty."""
        _, pq = arrow()
        files = ([self.path] if self.path.exists() else []) + self._part_files()
        tables = []
        for f in files:
            try:
                tables.append(pq.read_table(f))
            except Exception as exc:
                raise UserError(f"{f}: cannot read it as Parquet ({exc}); move it away to "
                                "run the campaign on, its points then run again") from exc
        tables = [t for t in tables if t.num_rows]
        return _concat(tables, list(self.params)) if tables else None

    def append(self, rows: Sequence[Mapping[str, Any]]) -> Path | None:
        """Rows as a new part, complete or not at all."""
        if not rows:
            return None
        _, pq = arrow()
        self.parts.mkdir(parents=True, exist_ok=True)
        self._seq += 1
        path = self.parts / f"part-{self.session}-{self._seq:05d}.parquet"
        table = to_table([{**r, "session": self.session} for r in rows], self.params)
        tmp = _tmp(path)
        try:
            pq.write_table(table, tmp)
            return _replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    def compact(self) -> Any | None:
        """The parts into ``results.parquet`` (one file, the campaign in its metadata),
        the parts then removed; returns the table."""
        _, pq = arrow()
        parts = self._part_files()
        table = self.read()
        if table is None:
            return None
        if parts or not self.path.exists():
            meta = {**(table.schema.metadata or {}),
                    META_KEY: json.dumps(self.meta, ensure_ascii=False).encode()}
            tmp = _tmp(self.path)
            try:
                pq.write_table(table.replace_schema_metadata(meta), tmp)
                _replace(tmp, self.path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
            for p in parts:
                p.unlink(missing_ok=True)
        return table

    def write_csv(self, table: Any) -> Path:
        """``results.csv`` beside the table (complete or not at all)."""
        import pyarrow.csv as pacsv

        path = self.dir / CSV
        tmp = _tmp(path)
        try:
            pacsv.write_csv(table, tmp)
            return _replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def is_campaign(path: Path) -> bool:
    """``path`` is a campaign's table or its directory (its campaign.json, no run's
    summary.json)."""
    if path.suffix == ".parquet":
        return True
    return (path.is_dir() and not (path / "summary.json").exists()
            and ((path / META).is_file() or (path / RESULTS).exists()))


def open_table(arg: str) -> tuple[Any, dict[str, Any], Path]:
    """``campaign show TABLE``: TABLE is a campaign's DIR or its results.parquet; the table
    (with any parts not yet compacted), the campaign's metadata and DIR."""
    p = Path(arg)
    d = p if p.is_dir() else p.parent
    meta_file = d / META
    if not (p.is_dir() and (meta_file.exists() or (p / RESULTS).exists())) and not (
            p.is_file() and p.suffix == ".parquet"):
        raise UserError(f"{arg}: not a campaign's table; give the campaign's directory (its "
                        f"--out DIR) or its {RESULTS}")
    meta: dict[str, Any] = {}
    if meta_file.exists():
        try:
            meta = json.loads(meta_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise UserError(f"{meta_file}: cannot read it ({exc})") from exc
    results = p if p.is_file() else d / RESULTS
    if not meta and results.exists():
        _, pq = arrow()
        raw = (pq.read_schema(results).metadata or {}).get(META_KEY)
        meta = json.loads(raw) if raw else {}
    table = ResultTable(d, meta, meta.get("params", {})).read()
    if table is None:
        raise UserError(f"{arg}: the campaign has no results yet; run it first "
                        "(hil-gateway campaign CAMPAIGN.toml --out DIR)")
    return table, meta, d
