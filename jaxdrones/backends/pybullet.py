"""The PyBullet backend: the same ``step(params, state, rpm) -> state`` as the JAX core, stepped by Bullet.

Bullet adds what the JAX core does not model: collisions with the ground, obstacles and other drones, and
rendering. Each simulated world is its own Bullet world (a ``DIRECT`` client, headless). A control step writes the
state into the drone bodies, holds the RPM command over ``sim_freq // ctrl_freq`` Bullet steps, and reads the state
back; nothing is kept between calls that the state does not carry (obstacles are fixed).

Forces, as in the paper's PyBullet update (docs/physics.md §3.2, §5, §6), re-applied before every Bullet step:

- each motor's force kf·rpm² (plus its ground-effect thrust) along body +z at its lever-arm point, so Bullet derives
  the roll and pitch torques from the geometry; the yaw reaction torque -Σ spin_i km rpm_i² about body z;
- drag (world frame, at the centre of mass) and downwash (the paper's: body -z, at the centre of mass; the
  per-rotor model's: each rotor's thrust change, added to its force at its lever-arm point), computed by the same
  functions as the JAX core (`jaxdrones.physics.aerodynamics`);
- gravity 9.8 m/s² (params), the gyroscopic term by Bullet's rigid-body solver;
- a step's `jaxdrones.physics.state.Disturbance`: its force (world frame, at the centre of mass) and torque (body
  frame), and its wind in the drag; with ``SimConfig.motor_dynamics`` the motors' speeds follow the command with the
  params' time constants before each Bullet step, as in the JAX core (docs/physics.md §3.3).

Differences from the original's PyBullet modes (docs/physics.md §14.3), so that both backends share one model:

- forces are applied in the *current* body frame (on the base, which Bullet keeps up to date), not through the
  propeller links, whose frames lag one step in the original (docs/physics.md §5.4);
- the lever-arm points are the explicit model's (``DroneParams.torque_arm``, from the URDF's ``arm`` and ``frame``):
  for the cf2x they sit at arm/√2 = 0.02807 m where the URDF's propeller links are at 0.028 m (docs/physics.md §3.1);
- Bullet's default velocity damping (docs/physics.md §5.2) is off unless ``damping=True``;
- mass, inertia and collision shape are taken from the same `DroneParams` as the JAX core (URDF inertia, as the
  original's main branch does), and the collision cylinder covers the propellers.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import weakref

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from jaxdrones.backends import RENDERERS, camera, require_pybullet, scene
from jaxdrones.physics import aerodynamics
from jaxdrones.physics.checks import check_disturbance, check_params_batch, check_rpm, check_rpm_shape
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.dynamics import Effects
from jaxdrones.physics.params import DroneParams, broadcast_params, pack_params, params_batch_shape
from jaxdrones.physics.rotations import join, quat_to_rotmat_c, split
from jaxdrones.physics.state import CONTACT_DRONE, CONTACT_GROUND, CONTACT_OBSTACLE, Disturbance, DroneState

pybullet = require_pybullet()

#: Renderers of the cameras: TinyRenderer (CPU, always there) or Bullet's OpenGL through EGL (headless GPU).
#: The keyword options of `PyBulletStep` (and of ``make_step(..., backend="pybullet")``).
OPTIONS = ("obstacles", "damping", "gui", "renderer")
_STATE_FIELDS = ("pos", "quat", "vel", "ang_vel", "rpm", "contact")
#: Where `_traced` splits the packed kinematics (pos 3, quat 4, vel 3, ang_vel 3, rpm 4).
_KINEMATIC_SPLITS = (3, 7, 10, 13)
#: Where pos, quat, vel, ang_vel and rpm lie in a drone's 17 packed floats.
_FIELD_SLICES = ((0, 3), (3, 7), (7, 10), (10, 13), (13, 17))
#: What a drone of a failed world reads: NaN kinematics and command, no contact.
_NAN_DRONE = ([math.nan] * 3, [math.nan] * 4, [math.nan] * 3, [math.nan] * 3, [math.nan] * 4, 0)


class _World:
    """One Bullet world: its client and the ids of what it holds."""

    def __init__(self, client: int, ground: int, obstacles: list[int]):
        self.client = client
        self.ground = ground
        self.obstacles = obstacles
        self.drones: list[int] = []
        self.geometry: list[dict] = []
        self.category = {ground: CONTACT_GROUND, **{b: CONTACT_OBSTACLE for b in obstacles}}
        self.drone_index: dict[int, int] = {}
        self.host = None  # the host params the world was last synced with
        self.jax_params = None  # this world's params as jax arrays, for the aerodynamic effects

    def disconnect(self) -> None:
        if self.client >= 0:
            try:
                pybullet.disconnect(physicsClientId=self.client)
            except pybullet.error:
                pass
            self.client = -1


def _disconnect_all(worlds: list[_World]) -> None:
    for world in worlds:
        world.disconnect()
    worlds.clear()


class PyBulletStep:
    """The PyBullet backend's control step; build it with ``jd.make_step(config, backend="pybullet", ...)``.

    Call it as ``step(params, state, rpm) -> state``, like the JAX backend: ``state`` is a `DroneState` with leading
    world axes ``[..., D, ...]`` (one Bullet world per world), ``rpm`` f[..., D, 4] in RPM, clipped to
    [0, max_rpm]. Called on concrete arrays, NumPy or JAX, it returns NumPy arrays: Bullet runs on the host, a JAX
    array is read into NumPy once, and building JAX arrays of the result would cost per field about as much as the
    step itself on the CPU, while every JAX function takes NumPy arrays as they are. Inside
    ``jit``, ``vmap`` or ``lax.scan`` (e.g. `jd.rollout`, the envs) the step runs as a host callback
    (`jax.pure_callback`). It is not differentiable. ``state.contact`` reports what each drone touched (ground,
    obstacle, drone). Bullet worlds are created on first use and released by `close` (or a ``with`` block, or
    garbage collection).

    A world whose input is not finite, or whose Bullet client fails, returns NaN for its drones and is rebuilt;
    the other worlds are unaffected.

    Float64 under ``jit``: turn it on globally (``jax.config.update("jax_enable_x64", True)``), not with the
    thread-local ``jax.enable_x64`` context, since host callbacks run on XLA's threads and JAX converts their
    outputs with the global setting there.

    Cameras: `camera_images` renders every drone's onboard camera (rgb, depth, segmentation) and `render` a
    third-person view of one world (for videos); `body_ids` maps segmentation ids to the ground, obstacles and
    drones. ``gui=True`` shows world 0 in PyBullet's window; it needs a display (on Linux an X server reachable
    through ``$DISPLAY``) and raises RuntimeError at construction without one.
    """

    #: The PyBullet backend renders (`camera_images`, `render`).
    has_cameras = True

    def __init__(
        self, config: SimConfig, *, obstacles=None, damping: bool = False, gui: bool = False, renderer: str = "tiny"
    ):
        if renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
        if config.kinks.mode != "exact":
            raise ValueError(
                f"the pybullet backend is not differentiable and steps the original's physics: "
                f"SimConfig.kinks must be 'exact', got {config.kinks.mode!r}"
            )
        if config.downwash_radius is not None:
            raise ValueError(
                f"the pybullet backend steps the original's downwash between every pair of drones: "
                f"SimConfig.downwash_radius must be None, got {config.downwash_radius!r}"
            )
        if gui:
            require_display()
        self.config = config
        self._effects = config.effects
        self.obstacles = scene.resolve_obstacles(obstacles)
        self.damping = bool(damping)
        self.gui = bool(gui)
        self.renderer = renderer
        self._worlds: list[_World] = []
        self._closed = False
        self._host_cache = (None, None, None)  # (params object, lead shape, host params)
        self._value_cache = (None, None)  # (params values and lead shape, host params)
        self._finalizer = weakref.finalize(self, _disconnect_all, self._worlds)

    # ----------------------------------------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Disconnect every Bullet world. The step cannot be called afterwards."""
        self._finalizer()
        self._closed = True

    def __enter__(self) -> PyBulletStep:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_worlds(self) -> int:
        """Number of Bullet worlds created so far."""
        return len(self._worlds)

    @property
    def clients(self) -> tuple[int, ...]:
        """The Bullet client ids of the worlds (for direct PyBullet calls, e.g. adding debug items)."""
        return tuple(w.client for w in self._worlds)

    # ----------------------------------------------------------------------------------------------- stepping
    def check_open(self) -> None:
        """Raise RuntimeError if the step was closed."""
        if self._closed:
            raise RuntimeError("this PyBullet step was closed; build a new one with jd.make_step(...)")

    def __call__(
        self, params: DroneParams, state: DroneState, rpm, disturbance: Disturbance | None = None
    ) -> DroneState:
        self.check_open()
        tracer = jax.core.Tracer
        if disturbance is not None:
            # One array [..., D, 9] (force, torque, wind; zero where not given), as the host step reads it.
            disturbance = check_disturbance(self.config, state, disturbance)
            parts = [
                jnp.zeros_like(state.pos) if x is None else x
                for x in (disturbance.force, disturbance.torque, disturbance.wind)
            ]
            disturbance = jnp.concatenate(parts, axis=-1)
        if (
            isinstance(state.pos, tracer)
            or isinstance(state.quat, tracer)
            or isinstance(rpm, tracer)
            or isinstance(params.mass, tracer)
            or isinstance(params.kf, tracer)
            or isinstance(disturbance, tracer)
        ):
            return self._traced(params, state, rpm, disturbance)
        if disturbance is not None:
            disturbance = np.asarray(disturbance, np.float64)
        if isinstance(state.pos, jax.Array):  # read into NumPy once, then the NumPy path
            state = DroneState(*(np.asarray(getattr(state, f)) for f in _STATE_FIELDS))
        if isinstance(rpm, jax.Array):
            rpm = np.asarray(rpm)
        n = self.config.n_drones
        if not (
            isinstance(rpm, np.ndarray)
            and rpm.dtype.kind in "fiu"
            and rpm.shape == state.rpm.shape
            and state.pos.shape[-2:] == (n, 3)
            and state.quat.shape[-2:] == (n, 4)
        ):
            dtype = rpm.dtype if hasattr(rpm, "dtype") else np.asarray(rpm).dtype
            check_rpm_shape(self.config, state, np.shape(rpm), dtype)  # raises the error, or passes for lists
            rpm = np.asarray(rpm, dtype=np.float64)
        host = self.host_params(params, state.pos)
        return DroneState(
            *self._host_step(
                host, [np.asarray(getattr(state, f)) for f in _STATE_FIELDS], rpm, strict=True, disturbance=disturbance
            )
        )

    def _traced(self, params: DroneParams, state: DroneState, rpm, disturbance=None) -> DroneState:
        rpm = check_rpm(self.config, state, rpm)
        check_params_batch(params, state)
        lead = state.pos.shape[:-1]
        shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state)
        # The callback's arguments are packed into a few arrays: JAX moves each argument separately per call.
        packed_params, unpack_params = pack_params(broadcast_params(params, lead), lead)
        kinematics = jnp.concatenate([state.pos, state.quat, state.vel, state.ang_vel, state.rpm], axis=-1)

        def callback(packed_params, kinematics, contact, rpm, *disturbance):
            fields = np.split(np.asarray(kinematics), _KINEMATIC_SPLITS, axis=-1) + [np.asarray(contact)]
            host = self.host_params(unpack_params(packed_params), fields[0], by_value=True)
            extra = np.asarray(disturbance[0], np.float64) if disturbance else None
            return DroneState(*self._host_step(host, fields, np.asarray(rpm, np.float64), disturbance=extra))

        extra = () if disturbance is None else (disturbance,)
        return jax.pure_callback(
            callback, shapes, packed_params, kinematics, state.contact, rpm, *extra, vmap_method="broadcast_all"
        )

    def host_params(self, params: DroneParams, pos: jax.Array | np.ndarray, by_value: bool = False) -> dict:
        """The host-side params (`_host_params`) for drone positions ``pos`` f[*L, D, 3], cached: by identity of
        ``params`` (concrete inputs, whose batch is checked here), or ``by_value`` (the fresh NumPy arrays of a
        callback)."""
        lead = tuple(pos.shape[:-1])
        if by_value:
            key = (lead, tuple((x.shape, x.tobytes()) for x in map(np.asarray, jax.tree.leaves(params))))
            if key != self._value_cache[0]:
                self._value_cache = (key, _host_params(params, lead))
            return self._value_cache[1]
        cached_params, cached_lead, host = self._host_cache
        if params is not cached_params or lead != cached_lead:
            if params_batch_shape(params) != lead:
                check_params_batch(params, DroneState(pos, None, None, None, None, None))
            host = _host_params(params, lead)
            self._host_cache = (params, lead, host)
        return host

    def _host_step(
        self,
        host: dict,
        fields: list[np.ndarray],
        rpm: np.ndarray,
        strict: bool = False,
        disturbance: np.ndarray | None = None,
    ) -> list[np.ndarray]:
        """Step NumPy state fields [*L, D, k] with host params (see `_host_params`); returns the new fields.
        ``disturbance``: None or f[*L, D, 9], each drone's force (world, N), torque (body, N·m) and wind (world,
        m/s).

        A world whose inputs are not all finite gives NaN; with ``strict``, a non-finite ``rpm`` raises instead.

        The per-drone work runs on Python floats (the Bullet API takes sequences), which for a few drones costs far
        less than NumPy's per-call overhead.
        """
        lead = fields[0].shape[:-1]
        n_drones = lead[-1]
        n_worlds = math.prod(lead[:-1])
        lists = [np.asarray(f).reshape(n_worlds, n_drones, -1).tolist() for f in fields[:5]]
        rpm = rpm.reshape(n_worlds, n_drones, 4).tolist()
        extra = None if disturbance is None else disturbance.reshape(n_worlds, n_drones, 9).tolist()
        self._ensure_worlds(n_worlds, host)
        flat, contact = [], []  # per drone: pos, quat, vel, ang_vel, rpm (17 floats); the contact bits
        for w, world in enumerate(self._worlds[:n_worlds]):
            inputs = [x[w] for x in lists] + [rpm[w]]
            result = None
            finite = math.isfinite(sum(sum(row) for x in inputs for row in x))
            if strict and not finite and not math.isfinite(sum(sum(row) for row in inputs[-1])):
                raise ValueError("rpm contains NaN or inf")
            if finite:
                try:
                    result = self._step_world(world, w, host, *inputs, None if extra is None else extra[w])
                except pybullet.error:
                    self._rebuild_world(w, host)
            for pos_d, quat_d, vel_d, ang_vel_d, rpm_d, contact_d in result or [_NAN_DRONE] * n_drones:
                flat.extend(pos_d)
                flat.extend(quat_d)
                flat.extend(vel_d)
                flat.extend(ang_vel_d)
                flat.extend(rpm_d)
                contact.append(contact_d)
        # One array, and a view of it per field: for a few drones NumPy's per-call cost is most of a step's.
        packed = np.array(flat, dtype=fields[0].dtype).reshape(lead + (17,))
        out = [
            packed[..., a:b] if field.dtype == packed.dtype else packed[..., a:b].astype(field.dtype)
            for (a, b), field in zip(_FIELD_SLICES, fields[: len(_FIELD_SLICES)], strict=True)
        ]
        return out + [np.array(contact, dtype=fields[5].dtype).reshape(lead)]

    def _step_world(self, world: _World, w: int, host: dict, pos, quat, vel, ang_vel, rpm_prev, rpm, extra=None):
        """One control step of world ``w``; every argument is a per-drone list of floats [D][k]; ``extra`` None or
        per drone (force world, torque body, wind world) as 9 floats.

        Returns per drone (pos, quat, vel, ang_vel, rpm, contact), ang_vel in the body frame and rpm clipped (with
        motor dynamics: the motors' speeds at the end of the step).
        """
        client, bodies = world.client, world.drones
        kf, km, spin, max_rpm = host["kf"][w], host["km"][w], host["prop_spin"][w], host["max_rpm"][w]
        command = [[min(max(r, 0.0), max_rpm[d]) for r in rpm_d] for d, rpm_d in enumerate(rpm)]
        lagged = self.config.motor_dynamics
        if lagged:  # docs/physics.md §3.3, as `dynamics.motor_response_c`: exp(-dt/τ) of each drone, rising/falling
            decay = [
                (_decay(up, self.config.dt), _decay(down, self.config.dt))
                for up, down in zip(host["motor_tau_up"][w], host["motor_tau_down"][w], strict=True)
            ]
        speeds, previous = command, rpm_prev
        for d, body in enumerate(bodies):
            q = _normalized(quat[d])
            pybullet.resetBasePositionAndOrientation(body, pos[d], q, physicsClientId=client)
            pybullet.resetBaseVelocity(body, vel[d], _rotate(q, ang_vel[d]), physicsClientId=client)
        effects = self._effects
        wind = extra is not None and effects.drag
        any_effect = effects.drag or effects.ground_effect or (effects.downwash and len(bodies) > 1)
        points = host["thrust_points"][w]
        contact = [0] * len(bodies)
        link, world_frame = pybullet.LINK_FRAME, pybullet.WORLD_FRAME
        if any_effect and world.jax_params is None:
            world.jax_params = jax.tree.map(jnp.asarray, DroneParams(**_world_slice(host["arrays"], w)))
        for sub in range(self.config.n_substeps):
            if lagged:
                speeds = [
                    [c + (r - c) * (up if c > r else down) for r, c in zip(r_d, c_d, strict=True)]
                    for r_d, c_d, (up, down) in zip(previous, command, decay, strict=True)
                ]
            if sub == 0 or lagged:
                # The motor model (docs/physics.md §3): f_i = kf rpm_i², yaw torque -Σ spin_i km rpm_i², as
                # `dynamics.motors_c`.
                thrust = [[kf[d] * r * r for r in rpm_d] for d, rpm_d in enumerate(speeds)]
                yaw = [
                    -km[d] * sum(s * r * r for s, r in zip(spin[d], rpm_d, strict=True))
                    for d, rpm_d in enumerate(speeds)
                ]
            lift, body_z, drag = thrust, None, None
            if any_effect:
                if sub > 0:
                    pos, quat, vel, _ = _read_kinematics(client, bodies)
                air = np.asarray([e[6:] for e in extra]) if wind else None
                lift, body_z, drag = (
                    np.asarray(x).tolist()
                    for x in _effect_forces(
                        effects,
                        world.jax_params,
                        np.asarray(pos),
                        np.asarray(quat),
                        np.asarray(vel),
                        np.asarray(thrust),
                        np.asarray(previous),
                        air,
                    )
                )
            elif sub > 0 and extra is not None:
                pos = _read_kinematics(client, bodies)[0]
            for d, body in enumerate(bodies):
                lift_d, points_d = lift[d], points[d]
                for i in range(4):
                    pybullet.applyExternalForce(
                        body, -1, (0.0, 0.0, lift_d[i]), points_d[i], link, physicsClientId=client
                    )
                pybullet.applyExternalTorque(body, -1, (0.0, 0.0, yaw[d]), link, physicsClientId=client)
                if body_z is not None and body_z[d] != 0.0:
                    pybullet.applyExternalForce(
                        body, -1, (0.0, 0.0, body_z[d]), (0.0, 0.0, 0.0), link, physicsClientId=client
                    )
                if drag is not None and effects.drag:
                    pybullet.applyExternalForce(body, -1, drag[d], pos[d], world_frame, physicsClientId=client)
                if extra is not None:  # the disturbance: a world force at the centre of mass, a body torque
                    pybullet.applyExternalForce(body, -1, extra[d][0:3], pos[d], world_frame, physicsClientId=client)
                    pybullet.applyExternalTorque(body, -1, extra[d][3:6], link, physicsClientId=client)
            previous = speeds
            pybullet.stepSimulation(physicsClientId=client)
            for point in pybullet.getContactPoints(physicsClientId=client):
                for me, other in ((point[1], point[2]), (point[2], point[1])):
                    d = world.drone_index.get(me)
                    if d is not None:
                        contact[d] |= world.category.get(other, 0)
        out = []
        for d, body in enumerate(bodies):
            p, q = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
            v, omega = pybullet.getBaseVelocity(body, physicsClientId=client)
            out.append((p, q, v, _rotate_inverse(q, omega), speeds[d], contact[d]))  # ω world → body: Rᵀ ω
        return out

    # ----------------------------------------------------------------------------------------------- worlds
    def _ensure_worlds(self, n_worlds: int, host: dict) -> None:
        """Create worlds up to ``n_worlds`` and make every world's drones match the params."""
        while len(self._worlds) < n_worlds:
            self._worlds.append(self._new_world(len(self._worlds)))
        for w in range(n_worlds):
            world = self._worlds[w]
            if world.host is not host:
                if world.geometry != host["geometry"][w]:
                    self._sync_drones(world, host["geometry"][w])
                world.jax_params = None
                world.host = host

    def _new_world(self, index: int) -> _World:
        if self.gui and index == 0:
            try:
                client = pybullet.connect(pybullet.GUI)
            except pybullet.error as err:
                raise RuntimeError(
                    f"PyBullet GUI could not open ({err}); it needs a display, and only one GUI per process"
                ) from None
            pybullet.configureDebugVisualizer(pybullet.COV_ENABLE_GUI, 0, physicsClientId=client)
        else:
            client = pybullet.connect(pybullet.DIRECT)
        if client < 0:
            raise RuntimeError("PyBullet could not create a physics client")
        pybullet.setGravity(0.0, 0.0, 0.0, physicsClientId=client)  # gravity is set from the params
        pybullet.setTimeStep(self.config.dt, physicsClientId=client)
        pybullet.setRealTimeSimulation(0, physicsClientId=client)
        if self.renderer == "egl":  # before any body: the plugin only draws bodies created after it is loaded
            _load_egl(client)
        ground = scene.load_ground(client)
        obstacles = [scene.load_obstacle(client, o) for o in self.obstacles]
        return _World(client, ground, obstacles)

    def _rebuild_world(self, w: int, host: dict) -> None:
        self._worlds[w].disconnect()
        self._worlds[w] = self._new_world(w)
        self._sync_drones(self._worlds[w], host["geometry"][w])

    def _sync_drones(self, world: _World, geometry: list[dict]) -> None:
        """Make the world's drone bodies match ``geometry`` (one dict per drone, see `scene.drone_geometry`)."""
        client = world.client
        gravity = geometry[0]["gravity"]
        pybullet.setGravity(0.0, 0.0, -gravity, physicsClientId=client)
        for d, geom in enumerate(geometry):
            if d < len(world.drones):
                old = world.geometry[d]
                if all(old[k] == geom[k] for k in geom if k not in ("mass", "inertia", "gravity")):
                    scene.set_drone_dynamics(client, world.drones[d], geom, self.damping)
                    continue
                pybullet.removeBody(world.drones[d], physicsClientId=client)
                world.drones[d] = scene.create_drone(client, geom, self.damping)
            else:
                world.drones.append(scene.create_drone(client, geom, self.damping))
        for body in world.drones[len(geometry) :]:
            pybullet.removeBody(body, physicsClientId=client)
        del world.drones[len(geometry) :]
        world.geometry = [dict(g) for g in geometry]
        world.drone_index = {body: d for d, body in enumerate(world.drones)}
        world.category.update({body: CONTACT_DRONE for body in world.drones})

    # ----------------------------------------------------------------------------------------------- cameras
    def camera_images(
        self,
        params: DroneParams,
        state: DroneState,
        *,
        width: int = 64,
        height: int = 48,
        fov: float = 60.0,
        near: float | None = None,
        far: float = 100.0,
    ) -> dict:
        """Render every drone's onboard camera (see `jaxdrones.backends.camera` for the camera model).

        The drones are first placed at ``state``'s poses (its velocities are not used), then each drone's camera
        is rendered with one ``pybullet.getCameraImage`` call: eye on body +x just in front of the drone's
        collision cylinder (``params.collision_radius`` + `camera.EYE_MARGIN` = 5 mm), looking along body +x with
        body +z up; vertical field of view ``fov``, aspect W/H (square pixels, focal length
        f = (H/2)/tan(fov/2) pixels). The original instead puts the eye L above the drone with world +z up and
        aspect 1.0 (docs/physics.md §8.5): a camera fixed to the frame that does not see its own drone is what a real
        onboard camera is. Renderer: TinyRenderer for ``renderer="tiny"``, OpenGL through EGL for ``"egl"``.

        Inputs follow the step's conventions: concrete arrays (NumPy or JAX) give NumPy images, and inside
        ``jit``/``vmap``/``scan`` the rendering runs as a host callback (`jax.pure_callback`); leading world
        axes ``[..., D]`` map to one Bullet world each (created here if no step has run yet).

        Args:
            params: DroneParams, batched like for the step (``[D]``, ``[W, D]``, ``[W, 1]`` or unbatched).
            state: DroneState with pos f[..., D, 3] m and quat f[..., D, 4] (x, y, z, w) body → world.
            width, height: image size, pixels, in [1, 8192] (the original's 64 × 48 by default).
            fov: vertical field of view, degrees, in (0, 180).
            near: near clipping plane, m; None: each drone's arm L (the original's near plane).
            far: far clipping plane, m (and the depth of pixels that see nothing).

        Returns:
            dict with ``"rgb"`` uint8[..., D, H, W, 4] (RGBA), ``"depth"`` float32[..., D, H, W] m along the
            optical axis (from Bullet's z-buffer z: far·near / (far − (far − near)·z)), ``"seg"``
            int32[..., D, H, W] Bullet body ids (-1: nothing; see `body_ids`). Row 0 is the top of the image.
            Inside ``jit``, a drone with a non-finite pose reads rgb 0, depth NaN and seg -1.

        Raises:
            ValueError: on a bad width/height/fov/near/far, a state whose pos/quat are not [..., D, 3]/[..., D, 4],
                params that do not line up with the state, or (outside ``jit``) a non-finite pose.
            RuntimeError: if the step was closed, or a world fails to render twice in a row.
        """
        return camera.camera_images(self, params, state, width=width, height=height, fov=fov, near=near, far=far)

    def render(
        self,
        params: DroneParams,
        state: DroneState,
        *,
        world: int = 0,
        width: int = 640,
        height: int = 480,
        target: ArrayLike | None = None,
        distance: float = 1.5,
        yaw: float = -30.0,
        pitch: float = -30.0,
    ) -> np.ndarray:
        """A third-person RGB image of one world, e.g. for a video frame (`jaxdrones.io.video.VideoWriter`).

        The world's drones are placed at ``state``'s poses; the camera orbits ``target`` as in PyBullet's
        ``computeViewMatrixFromYawPitchRoll`` (z up), with a 60° vertical field of view, aspect W/H, near 0.01 m
        and far 100 m, rendered by the step's renderer.

        Args:
            params: DroneParams, as for the step.
            state: DroneState with concrete (NumPy or JAX) pos f[..., D, 3] m and quat f[..., D, 4].
            world: which world, an index into the state's leading world axes flattened in C order.
            width, height: image size, pixels, in [1, 8192].
            target: f[3] m, world frame, the point looked at; None: the mean position of the world's drones.
            distance: camera distance from ``target``, m.
            yaw, pitch: camera yaw about world z and pitch (negative looks down), degrees.

        Returns:
            uint8[H, W, 3] RGB, row 0 at the top.

        Raises:
            ValueError: on a bad argument, traced inputs (call it outside ``jit``), or a non-finite pose.
            RuntimeError: if the step was closed.
        """
        return camera.render(
            self,
            params,
            state,
            world=world,
            width=width,
            height=height,
            target=target,
            distance=distance,
            yaw=yaw,
            pitch=pitch,
        )

    def body_ids(self, world: int = 0) -> dict:
        """The Bullet body ids of world ``world``, to read segmentation images (`camera_images`).

        Returns:
            dict with ``"ground"`` (int), ``"obstacles"`` (tuple, in the order of ``step.obstacles``) and
            ``"drones"`` (tuple, in state order). In a freshly built world these are 0, 1..K and K+1..K+D (the
            load order), but drone ids change when a drone's geometry changes between calls, so look them up.

        Raises:
            ValueError: if the world has not been created yet (call the step or `camera_images` first).
        """
        if not isinstance(world, int) or isinstance(world, bool) or not 0 <= world < len(self._worlds):
            raise ValueError(
                f"world must be an int in [0, {len(self._worlds)}) (the worlds created so far, "
                f"by calling the step or camera_images), got {world!r}"
            )
        w = self._worlds[world]
        return {"ground": w.ground, "obstacles": tuple(w.obstacles), "drones": tuple(w.drones)}


def _world_slice(arrays: dict, w: int) -> dict:
    """World ``w``'s entries of a dict of [W, ...] arrays."""
    return {k: v[w] for k, v in arrays.items()}


def _host_params(params: DroneParams, lead: tuple[int, ...]) -> dict:
    """Params as NumPy arrays [W, D, ...] plus what the Bullet worlds need, for a state of leading shape ``lead``."""
    lead = tuple(lead)
    n_drones, n_worlds = lead[-1], math.prod(lead[:-1])
    full = broadcast_params(jax.tree.map(np.asarray, params), lead, xp=np)
    arrays = {
        name: np.asarray(getattr(full, name), np.float64).reshape(
            (n_worlds, n_drones) + getattr(full, name).shape[len(lead) :]
        )
        for name in DroneParams.__dataclass_fields__
    }
    arm = arrays["torque_arm"]  # τx = Σ arm[0, i] f_i, τy = Σ arm[1, i] f_i  ⇔  f_i at (-arm[1, i], arm[0, i])
    points = np.stack([-arm[..., 1, :], arm[..., 0, :], arrays["prop_pos"][..., 2]], axis=-1)
    geometry = [
        [
            {**scene.drone_geometry({k: v[w, d] for k, v in arrays.items()}), "gravity": float(arrays["gravity"][w, d])}
            for d in range(n_drones)
        ]
        for w in range(n_worlds)
    ]
    return {
        **{k: arrays[k].tolist() for k in ("kf", "km", "prop_spin", "max_rpm", "motor_tau_up", "motor_tau_down")},
        "thrust_points": points.tolist(),
        "geometry": geometry,
        "arrays": arrays,
    }


def _decay(tau: float, dt: float) -> float:
    """exp(-dt/τ), 0 for τ ≤ 0: as `jaxdrones.physics.dynamics.motor_decay`."""
    return math.exp(-dt / tau) if tau > 0 else 0.0


@functools.partial(jax.jit, static_argnums=0)
def _effect_forces(effects: Effects, params: DroneParams, pos, quat, vel, thrust, rpm_prev, wind=None):
    """The aerodynamic effects of one world, by the JAX core's functions: per-motor lift (thrust + ground effect +
    per-rotor downwash) f[D, 4] N, the paper's downwash f[D] N along body z, and drag f[D, 3] N in the world frame
    (relative to ``wind`` f[D, 3] m/s when given)."""
    rotmat = quat_to_rotmat_c(split(quat))
    lift = split(thrust)
    if effects.ground_effect:
        extra = aerodynamics.ground_effect_thrust_c(params, pos[:, 2], rotmat[2], lift)
        lift = tuple(t + e for t, e in zip(lift, extra, strict=True))
    body_z = jnp.zeros(pos.shape[0], pos.dtype)
    if effects.downwash == "per_rotor" and pos.shape[0] > 1:
        change = aerodynamics.downwash_thrust_c(params, split(pos), rotmat, split(thrust))
        lift = tuple(f + c for f, c in zip(lift, change, strict=True))
    elif effects.downwash == "bounded" and pos.shape[0] > 1:
        total = jnp.sum(thrust, axis=-1)
        body_z = aerodynamics.downwash_force_c(params, split(pos), bounded=aerodynamics.BOUNDED_DOWNWASH, thrust=total)
    elif effects.downwash and pos.shape[0] > 1:
        body_z = aerodynamics.downwash_force_c(params, split(pos))
    if effects.drag:
        air = None if wind is None else split(wind)
        drag = join(aerodynamics.drag_force_c(params, split(vel), split(rpm_prev), air))
    else:
        drag = jnp.zeros_like(vel)
    return join(lift), body_z, drag


def _read_kinematics(client: int, bodies: list[int]):
    """pos, quat, vel and world-frame angular velocity of the drones, each a list (per drone) of tuples."""
    poses = [pybullet.getBasePositionAndOrientation(b, physicsClientId=client) for b in bodies]
    vels = [pybullet.getBaseVelocity(b, physicsClientId=client) for b in bodies]
    return [p for p, _ in poses], [q for _, q in poses], [v for v, _ in vels], [w for _, w in vels]


def _normalized(q) -> list[float]:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return [q[0] / n, q[1] / n, q[2] / n, q[3] / n]


def _rotate(q, v) -> list[float]:
    """Rotate a 3-vector by a unit quaternion (x, y, z, w): R v = v + 2w (u × v) + 2 u × (u × v)."""
    x, y, z, w = q
    tx, ty, tz = 2 * (y * v[2] - z * v[1]), 2 * (z * v[0] - x * v[2]), 2 * (x * v[1] - y * v[0])
    return [v[0] + w * tx + y * tz - z * ty, v[1] + w * ty + z * tx - x * tz, v[2] + w * tz + x * ty - y * tx]


def _rotate_inverse(q, v) -> list[float]:
    """Rᵀ v for a unit quaternion (x, y, z, w)."""
    return _rotate((-q[0], -q[1], -q[2], q[3]), v)


def _load_egl(client: int) -> None:
    """Load Bullet's EGL renderer plugin into a world, for hardware OpenGL rendering without a display."""
    import pkgutil

    egl = pkgutil.get_loader("eglRenderer")
    plugin = -1
    if egl is not None:
        plugin = pybullet.loadPlugin(egl.get_filename(), "_eglRendererPlugin", physicsClientId=client)
    if plugin < 0:
        raise RuntimeError(
            "renderer='egl': Bullet's EGL plugin could not be loaded on this machine; use "
            "renderer='tiny' (TinyRenderer, CPU)"
        )


def require_display() -> None:
    """Raise RuntimeError unless PyBullet's GUI can open a window.

    On Linux the GUI needs an X server: without one, ``pybullet.connect(pybullet.GUI)`` ends the whole process
    ("cannot connect to X server") instead of raising, so the display is probed first with ``XOpenDisplay``.
    """
    if not sys.platform.startswith("linux"):
        return
    display = os.environ.get("DISPLAY")
    hint = "; run headless (gui=False) and record frames with step.render / jaxdrones.video.VideoWriter"
    if not display:
        raise RuntimeError("gui=True needs a display, but DISPLAY is not set" + hint)
    import ctypes
    import ctypes.util

    try:
        x11 = ctypes.CDLL(ctypes.util.find_library("X11") or "libX11.so.6")
    except OSError:
        raise RuntimeError("gui=True needs libX11, which cannot be loaded" + hint) from None
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    handle = x11.XOpenDisplay(display.encode())
    if not handle:
        raise RuntimeError(f"gui=True needs a display, but X display {display!r} cannot be opened" + hint)
    x11.XCloseDisplay(handle)
