import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import plotly.graph_objects as go

    from canopy_kit import describe_path, open_bag, read_scan
    from canopy_kit.sim.plots import plot_scan_by_time

    return describe_path, go, mo, np, open_bag, plot_scan_by_time, plt, read_scan


@app.cell
def _(mo):
    args = mo.cli_args()
    bag_input = mo.ui.text(value=str(args.get("bag", "out/demo/pistachio_session/session")),
                           label="Bag (ROS1 .bag file or ROS2 folder)", full_width=True)
    bag_input
    return (bag_input,)


@app.cell
def _(bag_input, describe_path, mo):
    info = describe_path(bag_input.value)
    mo.vstack([
        mo.md(f"**{info['format']}**, {info['duration_s']:.1f} s"),
        mo.ui.table(info["topics"], selection=None),
    ])
    return (info,)


@app.cell
def _(info, mo):
    n_scans = max(t["count"] for t in info["topics"] if t["type"].endswith("PointCloud2"))
    scan_index = mo.ui.slider(0, n_scans - 1, value=min(100, n_scans - 1), label="scan", full_width=True,
                           show_value=True)
    scan_index
    return (scan_index,)


@app.cell
def _(bag_input, plot_scan_by_time, plt, read_scan, scan_index):
    scan = read_scan(bag_input.value, scan_index.value)
    fig_scan, ax_scan = plt.subplots(figsize=(7, 6))
    plot_scan_by_time(scan.xyz, scan.times if scan.times is not None else scan.xyz[:, 0] * 0, ax_scan)
    fig_scan
    return (scan,)


@app.cell
def _(go, np, scan):
    step = max(1, len(scan) // 30000)
    p = scan.xyz[::step]
    colour = scan.fields.get("intensity", p[:, 2])[::step]
    fig3d = go.Figure(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers",
                                   marker={"size": 1.5, "color": colour, "colorscale": "Viridis"}))
    fig3d.update_layout(scene={"aspectmode": "data"}, height=600, title="scan in 3-D (intensity)")
    fig3d
    return


@app.cell
def _(bag_input, np, open_bag, plt):
    with open_bag(bag_input.value) as bag:
        gnss = bag.gnss()
        odom = bag.odometry()
    fig_traj, ax_traj = plt.subplots(figsize=(6, 6))
    if odom is not None:
        ax_traj.plot(odom.position[:, 0], odom.position[:, 1], label=f"odometry topic ({len(odom.t)})")
    if gnss is not None:
        from canopy_kit import local_frame_for

        frame = local_frame_for(gnss)
        xyz = frame.to_local(gnss.latitude, gnss.longitude, gnss.altitude)
        ax_traj.plot(xyz[:, 0], xyz[:, 1], ".", ms=1, label="GNSS fixes (own frame)")
    ax_traj.set_aspect("equal")
    ax_traj.legend()
    ax_traj.set_title("trajectory sources in the bag")
    fig_traj
    return


if __name__ == "__main__":
    app.run()
