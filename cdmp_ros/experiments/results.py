"""The common results shape of every ``cdmp reproduce`` experiment."""
import json
import math
import os
from typing import Iterable, List, Optional, Sequence

from cdmp_ros.core.errors import ValidationError


def row(name: str, ours, paper=None, unit: str = '') -> dict:
    """One result row; ``paper`` is None where the paper gives no figure."""
    if isinstance(ours, float) and not math.isfinite(ours):
        ours = None
    return {'name': name, 'ours': ours, 'paper': paper, 'unit': unit}


def verification_rows(prefix: str, report) -> List[dict]:
    """Rows of an adaptation report's sampled verification: the largest per-step
    violation over the constraints, the trajectory-level violation (any constraint) with its
    95 % upper bound, and whether the claimed level holds by the check."""
    ver = report.verification
    if ver is None:
        return []
    step = max((c.per_step_max for c in ver.constraints), default=0.0)
    return [row(f'{prefix}.verified_per_step_max_pct', step * 100.0, None, '%'),
            row(f'{prefix}.verified_trajectory_pct', ver.trajectory_violation * 100.0, None,
                '%'),
            row(f'{prefix}.verified_trajectory_upper95_pct',
                ver.trajectory_violation_upper95 * 100.0, None, '%'),
            row(f'{prefix}.verified', bool(ver.holds), None,
                f'{ver.guarantee} level, {ver.n_samples} samples')]


def _fmt(value) -> str:
    if value is None:
        return '—'
    if isinstance(value, bool):
        return 'yes' if value else 'no'
    if isinstance(value, float):
        return f'{value:.4g}'
    return str(value)


def render_markdown(experiment: str, rows: Sequence[dict], notes: Iterable[str] = ()) -> str:
    lines = [f'# {experiment}', '', '| quantity | ours | paper | unit |', '|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['name']} | {_fmt(r['ours'])} | {_fmt(r['paper'])} | {r['unit']} |")
    notes = list(notes)
    if notes:
        lines += [''] + notes
    return '\n'.join(lines) + '\n'


def write_results(out_dir: str, experiment: str, rows: List[dict],
                  notes: Iterable[str] = (), extra: Optional[dict] = None) -> str:
    """Write ``results.json`` and ``results.md`` into ``out_dir``; returns the markdown."""
    os.makedirs(out_dir, exist_ok=True)
    names = [r['name'] for r in rows]
    if len(set(names)) != len(names):
        raise ValidationError(f'duplicate result row names in {experiment}: {names}')
    payload = {'experiment': experiment, 'rows': rows}
    if extra:
        payload.update(extra)
    with open(os.path.join(out_dir, 'results.json'), 'w') as f:
        json.dump(payload, f, indent=2)
    md = render_markdown(experiment, rows, notes)
    with open(os.path.join(out_dir, 'results.md'), 'w') as f:
        f.write(md)
    return md


def rows_by_name(results: dict) -> dict:
    """Map row name -> row of a loaded results.json."""
    return {r['name']: r for r in results['rows']}
