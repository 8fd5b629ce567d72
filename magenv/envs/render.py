"""Rendering of a trust env's episode: ``render_mode="rgb_array"`` frames, ``"human"`` windows, MP4 files.

A frame (H, W, 3) uint8 has two parts, stacked:

* the **scene** (top): the world at the last fused sample with the true sensor frame (solid axes, x red,
  y green, z blue) and the estimated one (thin, pale axes) drawn from the sensor's position. Simulated
  gimbal trials show MuJoCo's gimbal model (frames, tube, magnet) posed from the trial's truth
  (``joint_angles``, ``magnet_slide``); two-link trials the two links (``q_j``, ``q_true``; carriage
  fixed); hand-held trials a sensor box over a floor at its true position, the camera following; a
  recording (no world) shows the axes only.
* the **strip** (bottom): the total orientation error (°) and the policy's magnetometer trust over the
  last ``STRIP_SECONDS`` of the episode.

The scene is drawn by MuJoCo's renderer in an offscreen OpenGL context (backend "mujoco"), or, where no
GL context can be made, by matplotlib in 3-D (backend "matplotlib": axes only, no model). The choice is
made once per process (:func:`scene_backend`) and logged once on the ``magenv.render`` logger (a warning
for the fallback, naming why GL failed). The GL platform: ``MUJOCO_GL`` (``egl``, ``osmesa``, ``glfw``;
``disable`` forces matplotlib), else ``PYOPENGL_PLATFORM``, else OSMesa if its library is installed
(Debian: ``libosmesa6``), else EGL. Set ``MUJOCO_GL=egl`` for a GPU.

Nothing here runs in ``step``: a view is made at the first ``render()`` and reads the env's state then.
"""

from __future__ import annotations

import atexit
import ctypes.util
import importlib
import logging
import os
import sys
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from magenv import metrics
from magenv import quaternion as quat
from magenv.trial import META_SCENARIO, Trial

RENDER_MODES = ("rgb_array", "human")
RENDER_FPS = 30  # frames per second of a recorded video (one frame per env step)
WIDTH, SCENE_HEIGHT, STRIP_HEIGHT = 480, 320, 120  # pixels of a frame: scene above strip
STRIP_SECONDS = 10.0  # s of history in the strip
AXIS_LENGTH = 0.2  # m, drawn sensor axes
GL_PLATFORMS = ("egl", "osmesa", "glfw")
_GL_OFF = ("disable", "disabled", "off", "false", "0")
_TRUE_RGBA = ((0.9, 0.1, 0.1, 1.0), (0.1, 0.75, 0.1, 1.0), (0.15, 0.3, 1.0, 1.0))

log = logging.getLogger("magenv.render")


def check_render_mode(env_name: str, render_mode) -> None:
    """ValueError naming the modes unless ``render_mode`` is None or one of ``RENDER_MODES``; for "human",
    RuntimeError where no display exists (Linux without ``DISPLAY``/``WAYLAND_DISPLAY``)."""
    if render_mode is None:
        return
    if render_mode not in RENDER_MODES:
        raise ValueError(f"{env_name}: render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
    if render_mode == "human" and not has_display():
        raise RuntimeError(
            f"{env_name}: render_mode='human' needs a display (DISPLAY is unset); use 'rgb_array' "
            "(e.g. with gymnasium.wrappers.RecordVideo) on a machine without one"
        )


def has_display() -> bool:
    """Whether a window can be shown (always True off Linux)."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def magnetometer_trust(env) -> np.ndarray | None:
    """(N,) the policy's trust in the magnetometer per sample: the env's ``trust``, else 1 − ``lambdas`` (its
    IMU weight); None if it has neither."""
    trust = getattr(env, "trust", None)
    if trust is not None:
        return np.asarray(trust, float)
    lam = getattr(env, "lambdas", None)
    return None if lam is None else 1.0 - np.asarray(lam, float)


# ------------------------------------------------------------------ GL backend choice


def _gl_platform() -> str | None:
    """The GL platform to try (see the module docstring), or None for matplotlib."""
    choice = os.environ.get("MUJOCO_GL", "").strip().lower()
    if choice in _GL_OFF:
        return None
    if choice in GL_PLATFORMS:
        return choice
    pyopengl = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if pyopengl in ("egl", "osmesa"):
        return pyopengl
    if ctypes.util.find_library("OSMesa"):
        return "osmesa"
    if ctypes.util.find_library("EGL"):
        return "egl"
    return None


_BACKEND: tuple[str, str] | None = None  # ("mujoco", platform) or ("matplotlib", why), fixed at first use


def scene_backend() -> tuple[str, str]:
    """("mujoco", GL platform) if an offscreen GL context can be made here, else ("matplotlib", why not).

    Probed once per process (a 16×16 context, freed again) and logged once."""
    global _BACKEND
    if _BACKEND is None:
        platform = _gl_platform()
        if platform is None:
            _BACKEND = ("matplotlib", "no GL platform (MUJOCO_GL disabled, or neither OSMesa nor EGL installed)")
        else:
            try:
                ctx = open_gl_context(platform, 16, 16)
                ctx.free()
                _BACKEND = ("mujoco", platform)
            except Exception as exc:  # any failure of the GL stack means: no GL here
                _BACKEND = ("matplotlib", f"MuJoCo's {platform} context failed ({type(exc).__name__}: {exc})")
        if _BACKEND[0] == "mujoco":
            log.info("magenv rendering: MuJoCo offscreen renderer (%s)", _BACKEND[1])
        else:
            log.warning("magenv rendering: matplotlib fallback, axes only: %s", _BACKEND[1])
    return _BACKEND


def open_gl_context(platform: str, width: int, height: int):
    """A current MuJoCo GL context of ``platform`` (``mujoco.egl``/``osmesa``/``glfw`` ``GLContext``)."""
    if platform != "glfw":
        os.environ.setdefault("PYOPENGL_PLATFORM", platform)  # what mujoco.egl / mujoco.osmesa require
    ctx = importlib.import_module(f"mujoco.{platform}").GLContext(width, height)
    ctx.make_current()
    return ctx


# ------------------------------------------------------------------ scene models


class SceneModel(NamedTuple):
    """A world's MjModel, ``pose(data, i)`` (sets ``qpos`` to sample ``i``, returns the sensor's position in
    the world, m) and where the camera looks (``lookat``, m; ``distance``, m)."""

    model: Any
    pose: Callable
    lookat: tuple[float, float, float] | None  # None: follow the sensor
    distance: float


def _scene_model(trial: Trial) -> SceneModel | None:
    """The model of the trial's world posed from its truth, or None for a trial of no known world."""
    scenario = trial.meta.get(META_SCENARIO)
    if scenario is None:
        return None
    from magenv import scenarios

    try:
        world = scenarios.world_of(str(scenario))
    except ValueError:
        return None
    if world == "gimbal" and "joint_angles" in trial.truth:
        return _gimbal_model(trial)
    if world == "twolink" and "q_j" in trial.extra:
        return _twolink_model(trial)
    return _sensor_box_model(trial)


def _gimbal_model(trial: Trial) -> SceneModel:
    """The gimbal (``magenv/sim/gimbal.xml``): frames Z, Y, X at ``truth["joint_angles"]`` (ZYX, rad), the
    magnet at ``truth["magnet_slide"]`` (m along its tube; the tube where the model puts it)."""
    import mujoco

    from magenv.sim.gimbal import MODEL_PATH

    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    adr = {n: int(model.jnt_qposadr[model.joint(n).id]) for n in ("z", "y", "x", "slide")}
    site = model.site("imu").id
    joints, slide = trial.truth["joint_angles"], trial.truth.get("magnet_slide")

    def pose(data, i):
        data.qpos[[adr["z"], adr["y"], adr["x"]]] = joints[i]
        if slide is not None:
            data.qpos[adr["slide"]] = slide[i]
        mujoco.mj_kinematics(model, data)
        return data.site_xpos[site].copy()

    return SceneModel(model, pose, (0.0, 0.0, -0.06), 0.55)


def _twolink_model(trial: Trial) -> SceneModel:
    """The two links (``magenv/sim/twolink.xml``), carriage fixed: link j's hinges (jz, jy, jx) are the ZYX
    angles of ``extra["q_j"]``; link i's (iz, iy, ix) those of q0* ⊗ q_j* ⊗ q_i, q0 its fixed mounting
    quaternion in link j (each site frame is its link's frame). The axes are drawn at sensor i."""
    import mujoco

    from magenv.sim.twolink import MODEL_PATH

    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    adr = [int(model.jnt_qposadr[model.joint(n).id]) for n in ("jz", "jy", "jx", "iz", "iy", "ix")]
    q0 = np.asarray(model.body("link_i").quat, float)
    q_j, q_i = np.asarray(trial.extra["q_j"], float), trial.q_true
    rel = quat.mul(quat.conj(np.broadcast_to(q0, q_j.shape)), quat.mul(quat.conj(q_j), q_i))
    angles = np.concatenate([quat.to_euler_zyx(q_j), quat.to_euler_zyx(rel)], axis=1)
    site = model.site("imu_i").id

    def pose(data, i):
        if np.all(np.isfinite(angles[i])):
            data.qpos[adr] = angles[i]
        mujoco.mj_kinematics(model, data)
        return data.site_xpos[site].copy()

    centre = model.body("carriage").pos
    return SceneModel(model, pose, (0.4, 0.0, float(centre[2]) - 0.3), 1.4)


def _sensor_box_model(trial: Trial) -> SceneModel:
    """A sensor box (10 × 6 × 2 cm) on a free joint over a floor: at the true orientation, and at
    ``truth["position"]`` (m, ENU; the floor at z = 0) where the trial has one (the hand-held walker), the
    camera following it; else at 20 cm above the floor."""
    import mujoco

    spec = mujoco.MjSpec()
    spec.worldbody.add_light(pos=[0, 0, 3.0], dir=[0, 0, -1])
    floor = spec.worldbody.add_geom()
    floor.type, floor.size, floor.rgba = mujoco.mjtGeom.mjGEOM_PLANE, [0, 0, 0.5], [0.45, 0.47, 0.5, 1]
    body = spec.worldbody.add_body()
    body.add_freejoint()
    box = body.add_geom()
    box.type, box.size, box.rgba = mujoco.mjtGeom.mjGEOM_BOX, [0.05, 0.03, 0.01], [0.7, 0.7, 0.75, 1]
    model = spec.compile()
    q = trial.q_true
    where = trial.truth.get("position")
    where = np.broadcast_to([0.0, 0.0, 0.2], (trial.n, 3)) if where is None else np.asarray(where, float)

    def pose(data, i):
        data.qpos[:3] = where[i]
        if np.all(np.isfinite(q[i])):
            data.qpos[3:7] = q[i]
        mujoco.mj_kinematics(model, data)
        return data.xpos[1].copy()

    return SceneModel(model, pose, None, 0.55)


class MujocoScene:
    """The trial's MuJoCo model drawn offscreen, with the true and estimated sensor axes as arrows."""

    def __init__(self, built: SceneModel, platform: str, width: int, height: int):
        import mujoco

        self.mujoco = mujoco
        self.width, self.height = width, height
        self.model, self.pose = built.model, built.pose
        self.model.vis.global_.offwidth = max(width, self.model.vis.global_.offwidth)
        self.model.vis.global_.offheight = max(height, self.model.vis.global_.offheight)
        self.data = mujoco.MjData(self.model)
        self.ctx = open_gl_context(platform, width, height)
        self.con = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.con)
        self.scn = mujoco.MjvScene(self.model, 1000)
        self.opt = mujoco.MjvOption()
        self.cam = mujoco.MjvCamera()
        self.lookat = built.lookat
        self.cam.distance, self.cam.azimuth, self.cam.elevation = built.distance, 135.0, -25.0
        self.model.vis.headlight.ambient[:] = 0.35
        self.model.vis.headlight.diffuse[:] = 0.6
        self.rect = mujoco.MjrRect(0, 0, width, height)
        self.image = np.empty((height, width, 3), np.uint8)

    def _arrow(self, start, stop, width, rgba) -> None:
        scn, mj = self.scn, self.mujoco
        if scn.ngeom >= scn.maxgeom:
            return
        g = scn.geoms[scn.ngeom]
        mj.mjv_initGeom(g, mj.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.eye(3).ravel(), np.array(rgba, "f4"))
        mj.mjv_connector(g, mj.mjtGeom.mjGEOM_ARROW, width, np.asarray(start, float), np.asarray(stop, float))
        scn.ngeom += 1

    def draw(self, i: int, q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8: the world at sample ``i`` with the axes of ``q_true`` and ``q_est`` (sensor → ENU)."""
        mj = self.mujoco
        self.ctx.make_current()
        origin = self.pose(self.data, i)
        self.cam.lookat[:] = origin if self.lookat is None else self.lookat
        mj.mjv_updateScene(self.model, self.data, self.opt, None, self.cam, mj.mjtCatBit.mjCAT_ALL, self.scn)
        for q, width, pale in ((q_true, 0.008, 0.0), (q_est, 0.005, 0.45)):
            if np.all(np.isfinite(q)):
                axes = quat.to_matrix(q)  # columns: the sensor axes in ENU
                for k in range(3):
                    rgba = tuple(c + (1 - c) * pale for c in _TRUE_RGBA[k][:3]) + (1.0,)
                    self._arrow(origin, origin + AXIS_LENGTH * axes[:, k], width, rgba)
        mj.mjr_render(self.rect, self.scn, self.con)
        mj.mjr_readPixels(self.image, None, self.rect, self.con)
        return np.flipud(self.image).copy()  # OpenGL rows run bottom-up

    def close(self) -> None:
        """Free the MuJoCo render context, then the GL context (in that order: the first needs the second)."""
        if self.ctx is not None:
            self.ctx.make_current()
            self.con.free()
            self.ctx.free()
            self.ctx = None

    def __del__(self):
        if getattr(self, "ctx", None) is not None:
            self.close()


class AxesScene:
    """The true and estimated sensor axes in 3-D, drawn by matplotlib (no world model)."""

    def __init__(self, width: int, height: int, note: str):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        dpi = 100
        self.fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = self.fig.add_subplot(projection="3d")
        self.fig.subplots_adjust(0, 0, 1, 1)
        self.note = note

    def draw(self, i: int, q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
        ax = self.ax
        ax.cla()
        for q, lw, alpha in ((q_true, 3.0, 1.0), (q_est, 1.5, 0.45)):
            if np.all(np.isfinite(q)):
                axes = quat.to_matrix(q)
                for k in range(3):
                    end = axes[:, k]
                    ax.plot([0, end[0]], [0, end[1]], [0, end[2]], color=_TRUE_RGBA[k][:3], lw=lw, alpha=alpha)
        ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1), xlabel="E", ylabel="N", zlabel="U")
        ax.set_box_aspect((1, 1, 1))
        ax.text2D(0.02, 0.95, self.note, transform=ax.transAxes, fontsize=7)
        return _canvas_rgb(self.canvas)

    def close(self) -> None:
        self.fig.clear()


def _canvas_rgb(canvas) -> np.ndarray:
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


_Y_TOPS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0)  # ° error-axis tops of the strip (a few backgrounds)


class Strip:
    """Total error (°, black, left axis) and magnetometer trust (orange, right axis 0–1) over the last
    ``seconds`` of the episode (x: seconds before the last fused sample).

    The axes, ticks and labels are drawn by matplotlib once per error-axis top (one of ``_Y_TOPS``); the two
    curves are rasterised into the plot box with numpy each frame (a few ms, where a matplotlib redraw takes
    ~100 ms)."""

    def __init__(self, width: int, height: int, seconds: float = STRIP_SECONDS):
        self.width, self.height, self.seconds = width, height, seconds
        self._backgrounds: dict[float, tuple[np.ndarray, tuple[int, int, int, int]]] = {}

    def _background(self, top: float):
        if top not in self._backgrounds:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

            dpi = 100
            fig = Figure(figsize=(self.width / dpi, self.height / dpi), dpi=dpi)
            canvas = FigureCanvasAgg(fig)
            ax = fig.add_axes((0.1, 0.25, 0.8, 0.68))
            ax2 = ax.twinx()
            ax.set(xlim=(-self.seconds, 0.0), ylim=(0.0, top))
            ax2.set_ylim(-0.05, 1.05)
            ax.set_ylabel("error (°)", fontsize=7)
            ax.set_xlabel("t − now (s)", fontsize=7, labelpad=1)
            ax2.set_ylabel("mag trust", fontsize=7, color="tab:orange")
            for a in (ax, ax2):
                a.tick_params(labelsize=6)
            image = _canvas_rgb(canvas)
            x0, y0, x1, y1 = ax.get_window_extent().extents  # display pixels, origin bottom-left
            h = self.height
            box = (int(round(x0)) + 1, int(round(x1)) - 1, h - int(round(y1)) + 1, h - int(round(y0)) - 1)
            self._backgrounds[top] = (image, box)
        return self._backgrounds[top]

    def draw(self, t: np.ndarray, error: np.ndarray, trust: np.ndarray | None) -> np.ndarray:
        """(height, width, 3) uint8 of the curves ``error`` (°) and ``trust`` at times ``t`` (s, ascending)."""
        finite = error[np.isfinite(error)]
        peak = float(finite.max()) if finite.size else 0.0
        top = next((y for y in _Y_TOPS if peak <= y), _Y_TOPS[-1])
        image, (c0, c1, r0, r1) = self._background(top)
        image = image.copy()
        if len(t) < 2:
            return image
        cols = np.arange(c0, c1)
        when = t[-1] - self.seconds + (cols - c0 + 0.5) / (c1 - c0) * self.seconds
        inside = when >= t[0]
        curves = [(error, 0.0, top, (38, 38, 38))]
        if trust is not None:
            curves.append((trust, -0.05, 1.05, (255, 127, 14)))
        for values, lo, hi, rgb in curves:
            v = np.where(inside, np.interp(when, t, values), np.nan)
            rows = r1 - (np.clip(v, lo, hi) - lo) / (hi - lo) * (r1 - r0)
            _polyline(image, cols, rows, rgb)
        return image

    def close(self) -> None:
        self._backgrounds.clear()


def _polyline(image: np.ndarray, cols: np.ndarray, rows: np.ndarray, rgb) -> None:
    """Draw the curve through (rows[k], cols[k]) (fractional rows, NaN: gap) about 2 px wide into ``image``."""
    a, b = rows[:-1], rows[1:]
    ok = np.isfinite(a) & np.isfinite(b)
    lo = np.floor(np.minimum(a, b)[ok] - 0.5).astype(int)
    hi = np.ceil(np.maximum(a, b)[ok] + 0.5).astype(int)
    c = cols[:-1][ok]
    top, bottom = int(lo.min(initial=0)), int(hi.max(initial=0))
    if not c.size:
        return
    y = np.arange(top, bottom + 1)[:, None]
    mask = (y >= lo) & (y <= hi)
    rr, kk = np.nonzero(mask)
    image[np.clip(rr + top, 0, image.shape[0] - 1), c[kk]] = rgb


_LIVE: weakref.WeakSet = weakref.WeakSet()  # views to free before the interpreter shuts GL down


@atexit.register
def _close_live() -> None:
    for view in list(_LIVE):
        view.close()


class EpisodeView:
    """Frames of one env's episodes; the scene is rebuilt when the episode's trial changes."""

    def __init__(self, width: int = WIDTH, scene_height: int = SCENE_HEIGHT, strip_height: int = STRIP_HEIGHT):
        self.width, self.scene_height = width, scene_height
        self.backend = scene_backend()
        self.strip = Strip(width, strip_height)
        self.scene: Any = None  # MujocoScene or AxesScene, built at the first render()
        self._trial: Trial | None = None
        self._window: Any = None  # (figure, image) of render_mode 'human'
        _LIVE.add(self)

    def _scene_for(self, trial: Trial):
        if trial is not self._trial:
            if self.scene is not None:
                self.scene.close()
            kind, detail = self.backend
            built = _scene_model(trial) if kind == "mujoco" else None
            if built is not None:
                self.scene = MujocoScene(built, detail, self.width, self.scene_height)
            else:
                note = "no world model: axes only" if kind == "mujoco" else "no GL: axes only"
                self.scene = AxesScene(self.width, self.scene_height, note)
            self._trial = trial
        return self.scene

    def frame(self, env) -> np.ndarray:
        """(H, W, 3) uint8 of ``env`` (a TrustEnv after ``reset``) at its last fused sample."""
        runner = env._need_reset()
        trial = runner.trial
        i = max(0, min(runner.pos, trial.n) - 1)
        q_true, q_est = runner.q_true[i], runner.est[i]
        scene = self._scene_for(trial).draw(i, q_true, q_est)
        lo = max(0, i + 1 - int(round(STRIP_SECONDS * trial.rate)))
        t = np.arange(lo, i + 1) / trial.rate
        error = metrics.total_error(metrics.error_quaternion(runner.est[lo : i + 1], runner.q_true[lo : i + 1]))
        trust = magnetometer_trust(env)
        strip = self.strip.draw(t, error, None if trust is None else trust[lo : i + 1])
        return np.vstack([scene, strip])

    def show(self, env) -> None:
        """Draw the frame of ``env`` in a matplotlib window (``render_mode="human"``)."""
        import matplotlib.pyplot as plt

        image = self.frame(env)
        if self._window is None or not plt.fignum_exists(self._window[0].number):
            fig, ax = plt.subplots(figsize=(image.shape[1] / 100, image.shape[0] / 100), dpi=100)
            ax.set_axis_off()
            fig.subplots_adjust(0, 0, 1, 1)
            self._window = (fig, ax.imshow(image))
            plt.show(block=False)
        else:
            self._window[1].set_data(image)
        self._window[0].canvas.draw_idle()
        plt.pause(0.001)

    def close(self) -> None:
        if self.scene is not None:
            self.scene.close()
            self.scene, self._trial = None, None
        if self._window is not None:
            import matplotlib.pyplot as plt

            plt.close(self._window[0])
            self._window = None
        _LIVE.discard(self)


class RenderMixin:
    """``render()`` for a TrustEnv: "rgb_array" returns the frame, "human" shows it (also after each step)."""

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": RENDER_FPS}
    render_mode: str | None
    _view: EpisodeView | None = None

    @property
    def render_backend(self) -> tuple[str, str]:
        """("mujoco", GL platform) or ("matplotlib", why): how this process draws scenes."""
        return scene_backend()

    def _viewer(self) -> EpisodeView:
        if self._view is None:
            self._view = EpisodeView()
        return self._view

    def render(self):
        if self.render_mode is None:
            return None
        if self.render_mode == "human":
            self._viewer().show(self)
            return None
        return self._viewer().frame(self)

    def _close_view(self) -> None:
        if self._view is not None:
            self._view.close()
            self._view = None


def write_video(frames, path: str | Path, fps: int = RENDER_FPS) -> Path:
    """Write ``frames`` (an iterable of (H, W, 3) uint8 arrays, streamed) to the MP4 file ``path`` (H.264 by
    imageio-ffmpeg, which moviepy, hence ``magenv[video]``, installs)."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RuntimeError("writing a video needs imageio-ffmpeg: pip install 'magenv[video]'") from None
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"video file must end in .mp4, got {str(path)!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    try:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, macro_block_size=8, quality=6)
                writer.send(None)  # start the encoder
            writer.send(np.ascontiguousarray(frame))
    finally:
        if writer is not None:
            writer.close()
    if writer is None:
        raise ValueError(f"no frames to write to {path}")
    return path
