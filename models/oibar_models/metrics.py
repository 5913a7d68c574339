"""The paper's metrics (SPEC section 7) as tables. The metrics themselves (dt, dt_pct, dq,
summarize, score, mean_pose, the 5 % / 5 deg requirements) live in oibar.geometry.metrics,
shared with flight-side studies; they are re-exported here for the training code.
"""

from __future__ import annotations

from oibar.geometry.metrics import (  # noqa: F401
    ATT_REQ_DEG,
    POS_REQ_PCT,
    attitude_error_deg,
    mean_pose,
    position_error_m,
    position_error_pct,
    score,
    summarize,
)

TABLE_COLUMNS = [
    ("frames", "frames", "{:d}"),
    ("dt_mean_m", "dt mean (m)", "{:.3f}"),
    ("dt_median_m", "dt median (m)", "{:.3f}"),
    ("dt_mean_pct", "dt mean (%)", "{:.2f}"),
    ("dt_median_pct", "dt median (%)", "{:.2f}"),
    ("dq_mean_deg", "dq mean (deg)", "{:.2f}"),
    ("dq_median_deg", "dq median (deg)", "{:.2f}"),
    ("compliance_pos_pct", "pos <= 5 % (%)", "{:.2f}"),
    ("compliance_att_pct", "att <= 5 deg (%)", "{:.2f}"),
]


def markdown_table(
    rows: list[tuple[str, str, dict]], columns: list[tuple[str, str, str]] = TABLE_COLUMNS
) -> str:
    """rows: (sequence, model, summary) -> a markdown table as in the paper's per-sequence tables;
    `columns`: (summary key, heading, format). A key a summary lacks (or holds None) is an empty cell."""
    head = "| sequence | model | " + " | ".join(c[1] for c in columns) + " |"
    sep = "| --- | --- | " + " | ".join("---:" for _ in columns) + " |"
    lines = [head, sep]
    for seq, model, s in rows:
        cells = [fmt.format(s[k]) if s.get(k) is not None else "" for k, _, fmt in columns]
        lines.append(f"| {seq} | {model} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
