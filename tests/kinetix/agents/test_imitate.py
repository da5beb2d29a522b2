"""Imitation of a project level's scripted solution (kinetix.agents.imitate): the target distributions have the
solution's values as their mean, actions drawn from them follow them, and cloning the solution of a level the
general agent never solves gives an agent checkpoint that solves it; bad input is refused with a clear error."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kinetix.agents import checkpoint
from kinetix.agents.imitate import imitate, main, sample_actions, target_probabilities

LEVELS = Path(__file__).resolve().parents[3] / "levels"


def test_target_probabilities_have_the_solution_values_as_their_mean():
    motor, thrust = jnp.array([1.0, -0.25, 0.4, 3.0]), jnp.array([0.7, -1.0])
    p = np.asarray(target_probabilities(motor, thrust))
    assert p.shape == (16,) and (p >= 0).all()
    motors, thrusters = p[:12].reshape(4, 3), p[12:].reshape(2, 2)
    np.testing.assert_allclose(motors.sum(-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(thrusters.sum(-1), 1.0, atol=1e-6)
    # (off, +1, -1) per motor, as the multi_discrete action space orders them; values clipped to the ranges
    np.testing.assert_allclose(motors[:, 1] - motors[:, 2], [1.0, -0.25, 0.4, 1.0], atol=1e-6)
    np.testing.assert_allclose(motors[1], [0.75, 0.0, 0.25], atol=1e-6)
    np.testing.assert_allclose(thrusters[:, 1], [0.7, 0.0], atol=1e-6)


def test_sampled_actions_follow_the_target_probabilities():
    p = target_probabilities(jnp.array([0.5, -1.0, 0.0, 0.2]), jnp.array([0.3, 1.0]))
    actions = np.asarray(sample_actions(jax.random.key(0), jnp.broadcast_to(p, (20_000, 16))))
    assert actions.shape == (20_000, 6) and actions.dtype == np.int32
    assert abs((actions[:, 0] == 1).mean() - 0.5) < 0.02 and not (actions[:, 0] == 2).any()
    assert (actions[:, 1] == 2).all() and (actions[:, 2] == 0).all()
    assert abs((actions[:, 3] == 1).mean() - 0.2) < 0.02
    assert abs(actions[:, 4].mean() - 0.3) < 0.02 and (actions[:, 5] == 1).all()


@pytest.mark.slow
def test_cloning_thrust_hop_gives_an_agent_that_solves_it(tmp_path):
    # the shipped general agent solves thrust_hop in 0 of 100 attempts, and 2M env steps of PPO fine-tuning did not
    # change that (kinetix/agents/specialists/README.md)
    info = imitate(LEVELS / "thrust_hop.json", "general", tmp_path / "agent", episodes=16, epochs=60, attempts=32,
                   log=lambda line: None)
    assert info["demo_solve_rate"] >= 0.9 and info["demo_steps"] > 256
    assert info["solve_rate"] >= 0.9
    loaded = checkpoint.load(tmp_path / "agent")
    assert loaded.env["action"] == "multi_discrete" and loaded.info["level"].endswith("thrust_hop.json")


def test_bad_input_is_refused_with_a_clear_error(tmp_path, capsys):
    level = tmp_path / "mine.json"
    level.write_text((LEVELS / "car_right.json").read_text())
    assert main([str(level), "--out", str(tmp_path / "a")]) == 2
    assert "mine has no scripted solution" in capsys.readouterr().err
    car_right = str(LEVELS / "car_right.json")
    assert main([car_right, "--init", str(tmp_path / "nothing"), "--out", str(tmp_path / "a")]) == 2
    assert "unknown agent" in capsys.readouterr().err
    assert main([car_right, "--init", "random", "--out", str(tmp_path / "a")]) == 2
    assert "starts from a network" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([car_right, "--out", str(tmp_path / "a"), "--episodes", "0"])
    assert not (tmp_path / "a").exists()


def test_round_puts_each_binding_on_its_nearest_action():
    p = np.asarray(target_probabilities(jnp.array([0.6, -0.5, 0.49, -0.2]), jnp.array([0.5, 0.3]), "round"))
    motors, thrusters = p[:12].reshape(4, 3), p[12:].reshape(2, 2)
    np.testing.assert_array_equal(motors, [[0, 1, 0], [0, 0, 1], [1, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(thrusters, [[0, 1], [1, 0]])
    with pytest.raises(ValueError, match="dither 'floor'"):
        target_probabilities(jnp.zeros(4), jnp.zeros(2), "floor")
