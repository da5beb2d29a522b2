"""`kinetix bench train` measures the PPO settings it is given (epochs and minibatches change the update's
arithmetic, so a benchmark of the general run's settings must be able to use them), and refuses ones that cannot
split the batch before compiling anything."""

from kinetix.agents import bench
from kinetix.cli import main


def test_bench_train_uses_the_given_epochs_and_minibatches():
    result = bench.measure("s", num_envs=4, num_steps=2, chunks=1, updates_per_call=1, update_epochs=1,
                           num_minibatches=2)
    assert (result["update_epochs"], result["num_minibatches"]) == (1, 2)
    assert result["env_steps"] == 8 and result["steps_per_second"] > 0


def test_bench_train_refuses_minibatches_that_do_not_split_the_batch(capsys):
    command = ["bench", "train", "--sizes", "s", "--num-envs", "3", "--num-steps", "5", "--num-minibatches", "4"]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.startswith("kinetix bench train:") and "num_minibatches (4)" in err
