"""Matplotlib rendering of a reaching task: 3D backbone (tubes coloured), goal and tolerance
sphere, and the actuator forces/torques as arrows and bars."""

from __future__ import annotations

import numpy as np

from torchpvs.plotting import equalize_axes, plot_backbone

from .robots import solve_batch

__all__ = ["ReachRenderer"]


class ReachRenderer:
    """Draws robot ``i`` of a :class:`~envs.task.ReachBatch` into an RGB array (``draw``);
    with ``human=True`` also shows it in a pyplot window."""

    def __init__(self, robot, human: bool = False, size=(6.4, 5.2), dpi: int = 90):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.robot, self.human = robot, human
        if human:
            import matplotlib.pyplot as plt
            self._plt = plt
            self.fig = plt.figure(figsize=size, dpi=dpi)
        else:
            self.fig = Figure(figsize=size, dpi=dpi)
            FigureCanvasAgg(self.fig)

    def draw(self, task, i: int = 0) -> np.ndarray:
        robot, rb = self.robot, task.robots
        N = robot.n_tubes
        x = rb.x[i:i + 1]
        eq = solve_batch(robot, x, initial=rb.q[i:i + 1] if rb.q is not None else None)
        pts = eq.backbone(80)[0].numpy()
        scene = robot.scene.with_actuation(insertion=list(x[0, :N]), rotation=list(x[0, N:]))
        self.fig.clf()
        ax = self.fig.add_subplot(1, 1, 1, projection="3d")
        plot_backbone(scene, pts, ax=ax, title=f"{robot.name}: distance "
                      f"{1e3 * np.linalg.norm(rb.tip[i] - task.goal[i]):.2f} mm")
        goal = task.goal[i] * 1e3
        ax.scatter(*goal, color="tab:red", marker="*", s=80, depthshade=False, label="goal")
        # tolerance sphere
        u, v = np.mgrid[0:2 * np.pi:16j, 0:np.pi:9j]
        r = task.tolerance * 1e3
        ax.plot_wireframe(goal[0] + r * np.cos(u) * np.sin(v), goal[1] + r * np.sin(u) * np.sin(v),
                          goal[2] + r * np.cos(v), color="tab:red", linewidth=0.4, alpha=0.5)
        # actuator forces: arrows along -z at each carriage (positive = pulls back)
        tau = task.prev_action[i] * robot.action_scale
        span = max(robot.reach * 1e3 * 0.15, 5.0)
        for j in range(N):
            base = np.array([2.0 * (j + 1), 0.0, -min(x[0, j] * 1e3, span)])
            f = tau[j] / robot.force_scale[j] * span * 0.5
            ax.quiver(*base, 0.0, 0.0, -f, color=f"C{j}", linewidth=1.5,
                      arrow_length_ratio=0.3)
        text = "\n".join(f"tube {j + 1}: F = {tau[j]:+.2f} N, T = {1e3 * tau[N + j]:+.1f} mN·m"
                          for j in range(N))
        ax.text2D(0.02, 0.02, text, transform=ax.transAxes, fontsize=7)
        equalize_axes(ax)  # include the goal in the view
        ax.legend(loc="upper left", fontsize=7)
        self.fig.canvas.draw()
        img = np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()
        if self.human:
            self._plt.pause(0.001)
        return img

    def close(self) -> None:
        if self.human:
            self._plt.close(self.fig)
