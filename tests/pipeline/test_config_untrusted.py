"""Config layers are input, checked like a user's: no `${...}` interpolation is resolved (a secret of the environment
cannot leak into config.yaml or wandb), no float is NaN or infinite, and a dataset in object storage does not say
where a job runs: its ray.address, compile_cache.dir, tracking.dir and output_dir are ignored with a notice."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import typing

import pytest
from pipeline_test_helpers import environment

from kforge.pipeline.generation import ConfigError, JobConfig, to_yaml
from kforge.pipeline.generation.loading import read_config
from tests.pipeline.test_object_storage import BUCKET, S3_ENV

EXIT_USAGE = 2
SECRET = "not-to-be-leaked-1f2e"
SECRET_VARIABLE = "KFORGE_TEST_SECRET"


def float_keys(schema: type = JobConfig, prefix: str = "") -> list[str]:
    """Dotted keys of the schema's float fields (`float` or `float | None`)."""
    keys = []
    for name, hint in typing.get_type_hints(schema).items():
        if dataclasses.is_dataclass(hint):
            keys += float_keys(hint, f"{prefix}{name}.")
        elif hint is float or float in typing.get_args(hint):
            keys.append(f"{prefix}{name}")
    return keys


@pytest.fixture
def s3():
    """A moto S3 server on 127.0.0.1 with one bucket, the AWS_* environment pointing at it for this test only (a
    session's server of another module keeps its own)."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    endpoint = "http://{}:{}".format(*server.get_host_and_port())
    with environment(**S3_ENV, AWS_ENDPOINT_URL=endpoint):
        client = boto3.client("s3", endpoint_url=endpoint, region_name=S3_ENV["AWS_REGION"])
        client.create_bucket(Bucket=BUCKET)
        yield client
    server.stop()


def run_cli(*argv: str, cwd, **env) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "kforge", *argv]
    environment = {**os.environ, **env}
    return subprocess.run(command, capture_output=True, text=True, cwd=cwd, env=environment, timeout=120)


def test_an_interpolation_in_a_config_file_is_refused_by_the_cli_before_anything_runs(tmp_path):
    job_file = tmp_path / "job.yaml"
    job_file.write_text(f"split:\n  name: 1M/s\ntracking:\n  dir: ${{oc.env:{SECRET_VARIABLE}}}\n")
    finished = run_cli("run", str(job_file), "--scale", "tiny", cwd=tmp_path, **{SECRET_VARIABLE: SECRET})
    assert finished.returncode == EXIT_USAGE
    assert finished.stderr.strip().splitlines() == [
        f"error: {job_file}: tracking.dir: interpolations such as '${{oc.env:{SECRET_VARIABLE}}}' are not "
        "accepted; write the value itself"
    ]
    assert SECRET not in finished.stdout + finished.stderr
    assert list(tmp_path.iterdir()) == [job_file]  # no dataset, no logs


def test_an_interpolation_in_an_override_is_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"^overrides: split\.name: interpolations such as '\$\{oc\.env:HOME\}'"):
        read_config(None, ["split.name=${oc.env:HOME}", f"output_dir={tmp_path}"])
    with pytest.raises(ConfigError, match=r"^overrides: output_dir: interpolations such as '\$\{split\.name\}'"):
        read_config("1M/s", ["output_dir=${split.name}"])


def test_nan_and_infinity_are_refused_in_every_float_field():
    keys = float_keys()
    assert {"env.dense_reward_scale", "lease.stale_after_s", "ppo.learning_rate", "ray.gpus_per_worker"} <= set(keys)
    for key in keys:
        for value, shown in (("nan", "nan"), ("inf", "inf"), ("-inf", "-inf")):
            with pytest.raises(ConfigError, match=rf"^{key} must be a finite number, got {shown}$"):
                read_config("1M/s", [f"{key}={value}"])


def test_nan_in_a_config_file_is_refused_by_the_cli(tmp_path):
    job_file = tmp_path / "job.yaml"
    job_file.write_text("split:\n  name: 1M/s\nenv:\n  dense_reward_scale: .nan\n")
    finished = run_cli("run", str(job_file), "--scale", "tiny", cwd=tmp_path)
    assert finished.returncode == EXIT_USAGE
    assert finished.stderr.strip().splitlines() == ["error: env.dense_reward_scale must be a finite number, got nan"]
    assert list(tmp_path.iterdir()) == [job_file]


def test_a_remote_dataset_does_not_say_where_the_job_runs(s3, tmp_path, capsys):
    job = read_config("1M/s", ["output_dir=s3://elsewhere/ds"], scale="tiny")
    planted = dataclasses.replace(
        job,
        ray=dataclasses.replace(job.ray, address="attacker.example:6379"),
        compile_cache=dataclasses.replace(job.compile_cache, dir="/shared/planted-programs"),
        tracking=dataclasses.replace(job.tracking, dir="/shared/planted-tracking"),
    )
    s3.put_object(Bucket=BUCKET, Key="untrusted/config.yaml", Body=to_yaml(planted).encode())
    url = f"s3://{BUCKET}/untrusted"

    continued = read_config(url)
    assert continued.output_dir == url
    assert (continued.ray.address, continued.compile_cache.dir, continued.tracking.dir) == (
        None,
        "~/.cache/kforge/jax",
        None,
    )
    assert (continued.split, continued.ppo) == (job.split, job.ppo)  # what defines the data is kept
    notices = capsys.readouterr().err.strip().splitlines()
    where = f"{url}/config.yaml"
    assert notices == [
        f"notice: {where} sets output_dir='s3://elsewhere/ds'; ignored, a dataset does not say where a job runs",
        f"notice: {where} sets ray.address='attacker.example:6379'; ignored, a dataset does not say where a job runs",
        f"notice: {where} sets compile_cache.dir='/shared/planted-programs'; ignored, a dataset does not say where "
        "a job runs",
        f"notice: {where} sets tracking.dir='/shared/planted-tracking'; ignored, a dataset does not say where a job "
        "runs",
    ]
    chosen = read_config(url, ["ray.address=auto", "tracking.dir=/mine"], scale="full")  # the command sets them
    assert (chosen.ray.address, chosen.tracking.dir, chosen.work.levels_per_batch) == ("auto", "/mine", 128)
    assert [line.split(" sets ")[1].split("=")[0] for line in capsys.readouterr().err.splitlines()] == [
        "output_dir",
        "compile_cache.dir",
    ]  # no notice for a key the command sets


def test_a_remote_dataset_of_defaults_continues_without_a_notice(s3, capsys):
    url = f"s3://{BUCKET}/plain"
    s3.put_object(Bucket=BUCKET, Key="plain/config.yaml", Body=to_yaml(read_config("1M/s", [f"output_dir={url}"])))
    assert read_config(url).output_dir == url
    assert capsys.readouterr().err == ""
