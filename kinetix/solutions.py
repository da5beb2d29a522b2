"""Scripted solutions of the project's levels (levels/*.json): the proof that each can be solved, and the
demonstrations an agent can imitate where PPO cannot explore its way in (kinetix.agents.imitate).

A solution is a function `(t, sim) -> (motor binding values (4,), thruster binding values (2,))` of the agent step t
and the current SimState, written in jnp, so it runs under jit and vmap. Motor values are in [-1, 1], thruster
values in [0, 1] (the continuous action space's ranges). Bodies are read by their global index in the level's own
size class (polygons first, then circles from index P = 5 / 6 / 12 for s / m / l). Each is held for the frame skip,
as an agent's action is.
"""

from __future__ import annotations

import jax.numpy as jnp

FRAME_SKIP = 2  # every project level's
ENV_DT = FRAME_SKIP / 60.0  # seconds per agent step


def drive(m0=0.0, m1=0.0, m2=0.0, m3=0.0, t0=0.0, t1=0.0):
    """Binding values as the (motor (4,), thruster (2,)) float32 pair a solution returns."""
    def as_vector(values):
        return jnp.stack([jnp.asarray(v, jnp.float32) for v in values])

    return as_vector((m0, m1, m2, m3)), as_vector((t0, t1))


def joint_angle(sim, j):
    """Joint j's angle as its limits measure it: angle_b - angle_a - ref_angle."""
    joints = sim.joints
    return sim.bodies.angle[joints.b[j]] - sim.bodies.angle[joints.a[j]] - joints.ref_angle[j]


def balance_velocity(sim, base, pole, length, goal_x, v_max):
    """Cart-pole rule: the base velocity that keeps `pole` (pivot at its lower end) upright and brings the base to
    goal_x. Linearised, a pole of length L on a base accelerating at a tips as theta'' = 1.5 / L * (g theta + a)
    (theta counter-clockwise); choosing a places the closed-loop poles near 5 rad/s, and the outer loop leans the
    pole towards the goal (a lean is what accelerates the base)."""
    b = sim.bodies
    x, v = b.position[base, 0], b.velocity[base, 0]
    theta, omega = b.angle[pole], b.angular_velocity[pole]
    theta_ref = jnp.clip(0.12 * (x - goal_x) + 0.2 * v, -0.12, 0.12)
    k = 1.5 / length
    accel = -(9.81 + 25.0 / k) * (theta - theta_ref) - (7.0 / k) * omega
    return jnp.clip(v + accel * ENV_DT, -v_max, v_max)


def cartpole(t, sim):
    """Body 4 cart, 5 pole. The wheel motors track a velocity: action 1 = 2 * 6 rad/s * 0.2 m = 2.4 m/s."""
    return drive(balance_velocity(sim, 4, 5, 1.2, 3.6, 2.4) / 2.4)


def unicycle(t, sim):
    """Body 4 seat post, 5 wheel. The motor sets the wheel's spin relative to the post (2 * 6 rad/s at action 1),
    so a ground speed v needs a relative spin of v / r + the post's own spin."""
    v = balance_velocity(sim, 5, 4, 1.0, 3.6, 2.5)
    return drive((v / 0.25 + sim.bodies.angular_velocity[4]) / 12.0)


def lunar_lander(t, sim):
    """Body 4 lander; thruster 0 left engine, 1 right engine. Cruise at 3 m above the terrain to over the pad, then
    descend; the lean that gives the wanted horizontal speed is held by differential thrust."""
    b = sim.bodies
    (x, y), (vx, vy) = b.position[4], b.velocity[4]
    phi, omega = b.angle[4], b.angular_velocity[4]
    pad_x, pad_y = 3.9, 1.6
    above_pad = jnp.abs(x - pad_x) < 0.25
    vx_want = jnp.clip(1.2 * (pad_x - x), -1.0, 1.0)
    phi_want = -jnp.clip(0.6 * (vx_want - vx), -0.35, 0.35)
    vy_want = jnp.clip(2.0 * (jnp.where(above_pad, pad_y, 3.0) - y), -0.9, 0.6)
    lift = (0.61 + 0.5 * (vy_want - vy)) / jnp.cos(phi)  # 0.61: the hover share of both engines
    turn = 0.4 * (phi_want - phi) - 0.15 * omega
    return drive(t0=lift - turn, t1=lift + turn)


def pinball(t, sim):
    """Body 12 ball. Flip the left flipper when the ball rolls onto its middle; otherwise hold both flippers down."""
    x, y = sim.bodies.position[12]
    flip = (x > 1.55) & (x < 2.0) & (y < 1.3)
    return drive(jnp.where(flip, 1.0, -1.0), -1.0)


def grasper(t, sim):
    """Body 5 arm. Close the fingers, swing the arm (speed ramped up so the ball is not flung) to above the bin,
    and open the fingers once the arm has come to rest there."""
    arm, arm_speed = sim.bodies.angle[5], sim.bodies.angular_velocity[5]
    swing = jnp.clip(0.03 * (t - 15), 0.0, 1.0) * jnp.clip(2.0 * (1.3 - arm), -1.0, 1.0)
    at_rest_over_bin = (arm > 1.25) & (jnp.abs(arm_speed) < 0.1)
    return drive(swing, jnp.where(at_rest_over_bin, -0.3, 1.0))  # open gently: a fast finger flicks the ball


def obstacle_course(t, sim):
    """Body 4 car, 6 hammer rod. Creep to a waiting spot outside the hammer's low sweep, then dash as soon as the
    hammer has swung through the bottom to the right: the car follows it and is past before it swings back.
    (Driving flat out from the start gets the car hit.)"""
    x = sim.bodies.position[4, 0]
    phi, omega = sim.bodies.angle[6], sim.bodies.angular_velocity[6]
    hammer_leaving = (phi > -0.1) & (omega > 0.0)
    approach, waiting = x < 1.2, (x >= 1.2) & (x < 1.6)
    go = (x >= 1.6) | (waiting & hammer_leaving)
    return drive(jnp.where(go, 1.0, jnp.where(approach, 0.4, 0.0)))


def thruster_maze(t, sim):
    """Body 4 craft; thruster 0 lifts, 1 pushes right. Climb to the gap's height, cross it, drop and slide into
    the blue ball."""
    (x, y), (vx, vy) = sim.bodies.position[4], sim.bodies.velocity[4]
    before_gap = x < 2.9
    lift = jnp.where(before_gap, 0.6 + 1.5 * (3.45 - y) - 0.8 * vy, 0.0)
    push = ((y > 3.3) & (vx < 1.2)) | ((x > 2.7) & (y < 1.0))
    return drive(t0=lift, t1=push)


def ball_catch(t, sim):
    """Body 4 cart, 8 ball. Drive the cart under the ball's predicted landing point (a velocity command)."""
    (x, y), (vx, vy) = sim.bodies.position[8], sim.bodies.velocity[8]
    fall_time = (vy + jnp.sqrt(vy * vy + 2 * 9.81 * jnp.maximum(y - 0.8, 0.0))) / 9.81
    land_x = x + vx * fall_time
    cart_x = sim.bodies.position[4, 0]
    return drive(jnp.clip(2.0 * (land_x - cart_x), -2.2, 2.2) / 2.25)


def walker(t, sim):
    """Bodies 5/7 back/front thigh; joints 2/3 front/back knee. An open-loop gait found by a small random search
    (it still wins with every parameter perturbed by 3%): hips track sines of the absolute thigh angles, knees
    bend out of phase."""
    freq, hip_amp, hip_mid, knee_amp, knee_mid, leg_phase, knee_phase = 6.5, 0.39, 0.22, 0.37, -0.24, 2.3, -2.4
    phase = freq * t * ENV_DT
    target = jnp.stack([hip_mid + hip_amp * jnp.sin(phase), hip_mid + hip_amp * jnp.sin(phase + leg_phase),
                        knee_mid + knee_amp * jnp.sin(phase + knee_phase),
                        knee_mid + knee_amp * jnp.sin(phase + leg_phase + knee_phase)])
    angle = sim.bodies.angle
    current = jnp.stack([angle[7], angle[5], joint_angle(sim, 2), joint_angle(sim, 3)])
    return drive(*jnp.clip(4.0 * (target - current), -1.0, 1.0))


def crane(t, sim):
    """Body 5 jib. Lower the jib slowly (so the load does not swing into the red post) to the angle that sets the
    load on the platform."""
    jib = sim.bodies.angle[5]
    return drive(jnp.clip(0.02 * t, 0.0, 1.0) * jnp.clip(3.0 * (-1.1 - jib), -1.0, 1.0))


def pendulum_swing(t, sim):
    """Body 4 rod. The motor is too weak to lift the rod: pump energy by always pushing along the swing."""
    return drive(jnp.sign(sim.bodies.angular_velocity[4] + 1e-3))


SOLUTIONS = {
    # s
    "hamster_ball": lambda t, sim: drive(1.0),
    "pendulum_swing": pendulum_swing,
    "thrust_hop": lambda t, sim: drive(t0=sim.bodies.position[4, 0] < 1.6),  # thrust until the hop clears the red
    "unicycle": unicycle,
    # m
    "ball_catch": ball_catch,
    "car_ramp": lambda t, sim: drive(1.0),
    "car_right": lambda t, sim: drive(1.0),
    "octagon_roll": lambda t, sim: drive(t0=1.0),
    "seesaw": lambda t, sim: drive(-1.0),
    "thruster_maze": thruster_maze,
    # l
    "car_jump": lambda t, sim: drive(1.0),
    "cartpole": cartpole,
    "catapult": lambda t, sim: drive(jnp.where(t < 15, 0.0, -1.0)),  # let the ball settle, then fling
    "crane": crane,
    "drawbridge": lambda t, sim: drive(jnp.where(t < 40, 0.0, 1.0), -1.0),  # lower the bridge, then drive
    "grasper": grasper,
    "lunar_lander": lunar_lander,
    "obstacle_course": obstacle_course,
    "pinball": pinball,
    "tower_knockover": lambda t, sim: drive(jnp.clip(0.05 * t, 0.0, 1.0)),
    "walker": walker,
}
