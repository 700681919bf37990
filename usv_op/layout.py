"""The Foxglove layout for a fleet (`usv-op layout`): one layout for the live view and for the MCAP logs, since
both use the same topics and frames. docs/foxglove_layout.json is this for the four vessels of Table II.

A 3D panel in the `world` frame (the ground truth, when a simulation provides it, with every vessel's beliefs
hanging off its own `vessel/<id>` frame), and plots of what an operator watches per vessel: the commanded
surge speed, and the inputs refused so far (health counters of the status); and a Map panel of the GNSS fixes
(`/<id>/gnss`, foxglove.LocationFix) of a field trial's drivers, following the target's tag."""

from __future__ import annotations

from collections.abc import Sequence

from usv_op.view import load_sdk

GNSS_TAG = "target"   # the target tag's id (mission_log.gnss_truth.TARGET)
WATCHED = ("rejected_stale", "rejected_malformed", "rejected_shares_missing", "tick_errors", "overruns")


def status_path(vessel: str, field: str) -> str:
    """The message path of `field` in vessel `vessel`'s status (its topic quoted: it holds slashes)."""
    return f'"usv/{vessel}/status".{field}'


def fleet_layout(vessels: Sequence[str]) -> str:
    """The layout as Foxglove's JSON."""
    load_sdk()   # a clear word if foxglove-sdk is missing
    from foxglove import layouts

    surge = layouts.PlotPanel(title="commanded surge (m/s)", config=layouts.PlotConfig(paths=[
        layouts.PlotSeries(value=status_path(v, "command[0]"), label=f"vessel {v}") for v in vessels]))
    refused = layouts.PlotPanel(title="inputs refused and faults, by vessel", config=layouts.PlotConfig(paths=[
        layouts.PlotSeries(value=status_path(v, f"health.{name}"), label=f"{v}: {name}")
        for v in vessels for name in WATCHED]))
    scene = layouts.ThreeDeePanel(title="the fleet", config=layouts.ThreeDeeConfig(follow_tf="world"))
    # every LocationFix topic is drawn unless disabled; centred on the target's tag
    fixes = layouts.MapPanel(title="GNSS fixes (a field trial's truth)",
                             config=layouts.MapConfig(follow_topic=f"/{GNSS_TAG}/gnss"))
    return layouts.Layout(content=layouts.SplitContainer(direction="row", items=[
        layouts.SplitItem(proportion=2, content=scene),
        layouts.SplitItem(proportion=1, content=layouts.SplitContainer(direction="column", items=[
            layouts.SplitItem(content=surge), layouts.SplitItem(content=refused),
            layouts.SplitItem(content=fixes)]))])).to_json()

