"""A run's configuration: a ``--config`` file (or the defaults) with the options given on top.

The merging and its checks are one-line `ConfigError`s before any long work, so that an
unknown back end or matcher never costs a model load or a recording read.
"""

from __future__ import annotations

from typing import Any

from scanguard.errors import ConfigError

BACKENDS = ("gmapping", "graph", "frontend")
ODOMETRY_SOURCES = ("auto", "recorded", "simulated")
PRIORS = ("zero-motion", "constant-velocity")
MOTIONS = ("fused", "odometry", "guarded-matches")
RUNTIMES = ("onnx", "torch")
EXECUTORS = ("local", "ray")


def check_choice(option: str, value: str | None, allowed: tuple[str, ...]) -> str | None:
    """``value`` if it is one of ``allowed`` (None passes).

    Raises:
        ConfigError: ``value`` is not allowed (the message names ``option``).
    """
    if value is not None and value not in allowed:
        raise ConfigError(f"{option} must be one of {', '.join(allowed)}, not {value!r}")
    return value


def run_config(
    config: str | None,
    *,
    backend: str | None = None,
    odometry: str | None = None,
    prior: str | None = None,
    motion: str | None = None,
    matcher: str | None = None,
    particles: int | None = None,
    seed: int | None = None,
    relations: str | None = None,
    max_scans: int | None = None,
    allow_other_matcher: bool = False,
    relation_tolerance: float | None = None,
    compare: bool = True,
) -> Any:
    """The `RunConfig` of a ``config`` file (or the defaults) with the given options applied.

    Args:
        config: A RunConfig YAML file, or None for the defaults.
        backend: SLAM back end (gmapping, graph, frontend).
        odometry: auto, recorded or simulated.
        prior: zero-motion or constant-velocity (the option's spelling).
        motion: fused, odometry or guarded-matches (the option's spelling).
        matcher: The guard's scan matcher (a name of the matcher registry).
        particles: GMapping particles.
        seed: Seed of the particle filter.
        relations: Kümmerle reference relations file.
        max_scans: Only the first N scans.
        allow_other_matcher: Turn on judging a matcher the model was not trained for (never
            turns off what ``config`` turned on).
        relation_tolerance: Nearest-stamp tolerance (s) of the relation metric.
        compare: ``False`` (``--no-compare``): the main instance alone (never turns on what
            ``config`` turned off).

    Raises:
        ConfigError: An unknown choice or matcher, or a value the `RunConfig` refuses.
    """
    from scanguard.matching import get_matcher
    from scanguard.slam.config import RunConfig

    cfg = RunConfig.from_yaml(config) if config is not None else RunConfig()
    data = cfg.model_dump()
    if check_choice("--backend", backend, BACKENDS) is not None:
        data["backend"] = backend
    if check_choice("--odometry", odometry, ODOMETRY_SOURCES) is not None:
        data["odometry"] = odometry
    if check_choice("--prior", prior, PRIORS) is not None:
        data["prior"] = str(prior).replace("-", "_")
    if check_choice("--motion", motion, MOTIONS) is not None:
        data["motion"] = str(motion).replace("-", "_")
    if matcher is not None:
        data["matcher"] = matcher
    if allow_other_matcher:  # the flag only turns it on; a --config file may already have
        data["allow_other_matcher"] = True
    # an unknown name (option or --config file) is a one-line error before any long work
    get_matcher(str(data["matcher"]))
    if relations is not None:
        data["relations"] = relations
    if max_scans is not None:
        data["max_scans"] = max_scans
    if relation_tolerance is not None:
        data["relation_tolerance"] = relation_tolerance
    if not compare:
        data["compare"] = False
    if particles is not None:
        data["gmapping"]["particles"] = particles
    if seed is not None:
        data["gmapping"]["seed"] = seed
    # validated by the model: --max-scans 1 or --particles 0 are one-line errors
    return RunConfig.from_dict(data, source="command-line options")


def check_odom_topic(seq: Any, odom_topic: str | None, cfg: Any) -> None:
    """Never ignore ``--odom-topic`` silently: fail when the run cannot use that odometry.

    Raises:
        ConfigError: The run would not use the odometry of ``odom_topic``.
    """
    if odom_topic is None or cfg.motion == "guarded_matches":
        return
    if cfg.odometry == "simulated":
        raise ConfigError(
            f"--odom-topic {odom_topic}: not used with --odometry simulated (odometry made "
            "from the reference); drop one of the two"
        )
    if seq.odometry is None:
        raise ConfigError(f"--odom-topic {odom_topic}: {seq.name} has no odometry there")
    if seq.reference_kind == "corrected_log":
        raise ConfigError(
            f"--odom-topic {odom_topic}: {seq.name} is a corrected log, whose odometry is the "
            "corrected poses (the reference), so it is never used as odometry; drop "
            "--odom-topic (the run then uses a motion prior) or use the raw log"
        )
