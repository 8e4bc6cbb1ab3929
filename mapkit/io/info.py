"""``mapkit info``: what a drive log holds, per stream, read in one streaming pass.

Only GPS payloads are decoded (for distance and fix quality); every other stream is summarised from
its timestamps, so a multi-GB log is scanned at disk speed with constant memory.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from mapkit.core.geodesy import LocalFrame, path_length_m
from mapkit.core.runio import progress_bar
from mapkit.core.types import GpsFix, GpsStatus, StreamKind
from mapkit.io import open_log


def summarize(path: str | Path, format: str | None = None, progress: bool = False) -> dict[str, Any]:
    """A JSON-ready summary of a log: streams with counts, rates and spans; GPS distance and quality."""
    with open_log(path, format=format) as log:
        streams = log.streams()
        kinds = {s.topic: s for s in streams}
        gps_topics = {s.topic for s in streams if s.kind == StreamKind.GPS}
        stamps: dict[str, list[int]] = defaultdict(list)
        total = sum(s.count or 0 for s in streams) or None
        bar = _bar(total, progress)
        for topic, stamp in log.stamps():
            stamps[topic].append(stamp)
            bar.update(1)
        bar.close()
        fixes: dict[str, list[GpsFix]] = {t: [] for t in gps_topics}
        for msg in log.messages(topics=sorted(gps_topics)) if gps_topics else ():
            fixes[msg.topic].append(msg.record)
        truncated_at = getattr(log, "truncated_at", None)
        out_streams = []
        for topic, info in kinds.items():
            st = np.asarray(stamps.get(topic, []), dtype=np.int64)
            row: dict[str, Any] = {
                "topic": topic,
                "kind": info.kind.value,
                "type": info.msgtype,
                "count": int(len(st)),
            }
            if len(st):
                start, end = int(st.min()), int(st.max())
                dur = (end - start) * 1e-9
                row.update(
                    start_ns=start,
                    end_ns=end,
                    duration_s=round(dur, 6),
                    rate_hz=round((len(st) - 1) / dur, 3) if dur > 0 else None,
                    out_of_order=int(np.sum(np.diff(st) < 0)),
                    duplicate_stamps=int(np.sum(np.diff(st) == 0)),
                )
            out_streams.append(row)
        summary = {
            "log": str(path),
            "format": log.format_name,
            "messages_read": int(sum(len(v) for v in stamps.values())),
            "truncated_at_byte": truncated_at,
            "streams": out_streams,
            "gps": {t: _gps_quality(f) for t, f in fixes.items()},
        }
        return summary


def _gps_quality(fixes: list[GpsFix]) -> dict[str, Any]:
    status = Counter(GpsStatus(int(f.status)).name if int(f.status) in (-1, 0, 1, 2) else str(f.status) for f in fixes)
    good = [f for f in fixes if f.has_fix]
    out: dict[str, Any] = {
        "fixes": len(fixes),
        "with_fix": len(good),
        "fix_fraction": round(len(good) / len(fixes), 4) if fixes else 0.0,
        "status_counts": dict(status),
    }
    if good:
        lat = np.array([f.lat_deg for f in good])
        lon = np.array([f.lon_deg for f in good])
        alt = np.array([f.alt_m for f in good])
        frame = LocalFrame(float(lat[0]), float(lon[0]), float(alt[0]))
        enu = frame.geodetic_to_enu(lat, lon, alt)
        sigmas = np.array([f.horizontal_sigma_m for f in good])
        steps = np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1)
        out.update(
            distance_m=round(path_length_m(enu[:, :2]), 2),
            extent_m=round(float(np.ptp(enu[:, 0]) if len(enu) else 0.0), 2),
            median_horizontal_sigma_m=None if np.all(np.isnan(sigmas)) else round(float(np.nanmedian(sigmas)), 3),
            max_step_m=round(float(steps.max()), 2) if len(steps) else 0.0,
            utm_crs_epsg=int(frame.utm_epsg),
        )
    return out


def format_summary(summary: dict[str, Any]) -> str:
    """A fixed-width table for people."""
    lines = [f"{summary['log']}  ({summary['format']}, {summary['messages_read']} messages)"]
    if summary.get("truncated_at_byte") is not None:
        lines.append(
            f"  ! log damaged near byte {summary['truncated_at_byte']}: the damaged part is skipped (the warnings say "
            "what)"
        )
    header = f"  {'topic':<34} {'type':<30} {'count':>7} {'rate Hz':>8} {'span s':>9}"
    lines += [header, "  " + "-" * (len(header) - 2)]
    for s in summary["streams"]:
        rate = "" if s.get("rate_hz") is None else f"{s['rate_hz']:.2f}"
        span = "" if s.get("duration_s") is None else f"{s['duration_s']:.2f}"
        flag = ""
        if s.get("out_of_order") or s.get("duplicate_stamps"):
            flag = f"  ({s['out_of_order']} out of order, {s['duplicate_stamps']} duplicate stamps)"
        lines.append(f"  {s['topic']:<34} {s['type']:<30} {s['count']:>7} {rate:>8} {span:>9}{flag}")
    for topic, g in summary["gps"].items():
        if g.get("with_fix"):
            sigma = g.get("median_horizontal_sigma_m")
            sigma_txt = "unknown" if sigma is None else f"{sigma:.2f} m"
            lines.append(
                f"  GPS {topic}: {g['distance_m']:.1f} m covered, {g['with_fix']}/{g['fixes']} fixes "
                f"({100 * g['fix_fraction']:.0f}%), median sigma {sigma_txt}, largest step {g['max_step_m']:.1f} m"
            )
        else:
            lines.append(f"  GPS {topic}: no valid fix among {g['fixes']} messages")
    return "\n".join(lines)


def _bar(total: int | None, enabled: bool):
    return progress_bar(total, enabled, "scanning", "msg", leave=False)
