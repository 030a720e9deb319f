"""The ``uwb-env`` command line: one small function pair (arguments, handler) per subcommand."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path


class ArgumentError(ValueError):
    """A command-line argument that cannot work: printed as one line naming it, exit status 2."""


def load_overrides(path: str | None, option: str = "--config") -> dict:
    """Read a YAML/JSON mapping of config overrides (``None`` -> empty)."""
    if path is None:
        return {}
    import yaml

    if not Path(path).is_file():
        raise ArgumentError(f"{option} {path}: no such file")
    with open(path) as f:
        try:
            data = yaml.safe_load(f) or {}
        except yaml.YAMLError as err:
            raise ArgumentError(f"{option} {path}: not YAML/JSON ({str(err).splitlines()[0]})") from err
    if not isinstance(data, dict):
        raise ArgumentError(f"{option} {path}: expected a mapping at the top level")
    return data


def check_policies(specs: list[str] | None) -> list[str] | None:
    """Resolve ``rllib:`` paths to absolute ones (Ray reads a relative path as a URI without a
    scheme) and build every policy once, so a bad spec fails before any episode runs."""
    if not specs:
        return specs
    from uwb_env.agents.registry import make_policy

    resolved = []
    for spec in specs:
        name, _, param = spec.partition(":")
        if name == "rllib" and param and "://" not in param:
            spec = f"rllib:{Path(param).expanduser().resolve()}"
        try:
            make_policy(spec)
        except (ValueError, OSError, ImportError) as err:
            raise ArgumentError(f"--policies {spec}: {str(err).splitlines()[0] if str(err) else type(err).__name__}") \
                from err
        resolved.append(spec)
    return resolved


def _simulate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--steps", type=int, default=600, help="simulation steps (default 600)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--config", default=None, help="YAML/JSON file with SimConfig overrides")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _simulate(args: argparse.Namespace) -> int:
    from uwb_env.config import SimConfig
    from uwb_env.summary import simulate_summary

    summary = simulate_summary(
        SimConfig.from_dict(load_overrides(args.config)), steps=args.steps, seed=args.seed
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():
            print(f"{key:44s} {value}")
    return 0


def _evaluate_args(p: argparse.ArgumentParser) -> None:
    from uwb_env.training.evaluate import add_arguments

    add_arguments(p)


def _evaluate(args: argparse.Namespace) -> int:
    from uwb_env.training.evaluate import args_from_namespace, main

    load_overrides(args.config)  # a missing file fails here, before any work
    args.policies = check_policies(args.policies)
    main(args_from_namespace(args))
    return 0


def _tune_args(p: argparse.ArgumentParser) -> None:
    from uwb_env.training.tune import add_arguments

    add_arguments(p)


def _tune(args: argparse.Namespace) -> int:
    from uwb_env.training.tune import args_from_namespace, main

    main(args_from_namespace(args))
    return 0


def _train_args(p: argparse.ArgumentParser) -> None:
    from uwb_env.training.train import add_arguments

    p.add_argument("--backend", choices=("sb3", "rllib"), default="sb3",
                   help="sb3: stable-baselines3 PPO/A2C/DQN on this machine; rllib: Ray RLlib PPO, locally or on "
                        "a cluster (needs the 'cluster' extra; `python -m uwb_env.training.train_rllib --help`)")
    add_arguments(p)
    p.add_argument("--iterations", type=int, default=20, help="rllib: training iterations")
    p.add_argument("--address", default=None, help="rllib: Ray cluster address (default: a local instance)")
    p.add_argument("--num-env-runners", type=int, default=1, help="rllib: sampling workers")


def _train(args: argparse.Namespace) -> int:
    if args.backend == "rllib":
        try:
            import ray  # noqa: F401

            from uwb_env.training.train_rllib import Args, main
        except ImportError:
            print("uwb-env train --backend rllib: needs the 'cluster' extra: pip install 'uwb-env[cluster]'",
                  file=sys.stderr)
            return 2
        out = args.out if args.out != "runs/train" else "runs/rllib"
        load_overrides(args.env_config, "--env-config")
        record = main(Args(iterations=args.iterations, out=out, seed=args.seed, address=args.address,
                           num_env_runners=args.num_env_runners, hp=args.hp, env_config=args.env_config,
                           resume=args.resume))
        print(json.dumps({k: record[k] for k in ("iterations_done", "num_timesteps", "training_wall_s")}, indent=1))
        print(f"checkpoint: {out}/checkpoint  (evaluate: uwb-env evaluate --policies rllib:{out}/checkpoint fixed:10)")
        return 0
    try:
        import stable_baselines3  # noqa: F401

        from uwb_env.training.train import args_from_namespace, main
    except ImportError:
        print("uwb-env train: needs the 'train' extra: pip install 'uwb-env[train]'", file=sys.stderr)
        return 2
    load_overrides(args.env_config, "--env-config")
    record = main(args_from_namespace(args))
    print(json.dumps({k: record[k] for k in ("num_timesteps", "training_wall_s", "env_steps_per_s")}, indent=1))
    print(f"model: {args.out}/model.zip  (evaluate: uwb-env evaluate --policies learned:{args.out}/model.zip fixed:10)")
    return 0


def _train_anchor_set_args(p: argparse.ArgumentParser) -> None:
    from uwb_env.training.train_anchor_set import add_arguments

    add_arguments(p)


def _train_anchor_set(args: argparse.Namespace) -> int:
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        print("uwb-env train-anchor-set: needs the 'train' extra: pip install 'uwb-env[train]'", file=sys.stderr)
        return 2
    from uwb_env.training.train_anchor_set import args_from_namespace, main, report

    print(report(main(args_from_namespace(args))))
    model = f"{args.out}/best/model.zip"
    print(f"model: {model}  (evaluate: uwb-env evaluate --policies learned:{model})")
    return 0


def _emulate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--config", default=None, help="YAML/JSON file with SimConfig overrides (the emulated scene)")
    p.add_argument("--socket", action="store_true", help="serve socket://127.0.0.1:PORT instead of ptys")
    p.add_argument("--duration", type=float, default=None, help="seconds to run (default: until Ctrl-C)")
    p.add_argument("--hang-anchor", action="store_true", help="fault: the TIERS anchor never answers")
    p.add_argument("--truncate-rows", type=float, default=0.0, help="fault: probability a matrix row is cut")
    p.add_argument("--garbage", type=float, default=0.0, help="fault: probability of garbage bytes per chunk")
    p.add_argument("--drop-chars", type=float, default=0.0, help="fault: probability per dropped character")
    p.add_argument("--delay", type=float, default=0.0, help="fault: extra response latency (s)")
    p.add_argument("--tag-firmware", choices=("pans", "tiers"), default="pans",
                   help="tags: stock PANS (ranging to a PANS anchor set) or the TIERS localization build")
    p.add_argument("--all-pans", action="store_true",
                   help="the all-PANS deployment: a stock-PANS anchor per port (role switching), PANS tags")


def _emulate(args: argparse.Namespace) -> int:

    from uwb_env.config import SimConfig
    from uwb_env.hardware.emulator import Faults, Scene, standard_setup

    common = dict(garbage_probability=args.garbage, drop_char_probability=args.drop_chars,
                  response_delay_s=args.delay)
    scene = Scene(SimConfig.from_dict(load_overrides(args.config)), seed=args.seed)
    faults = {"anchor": Faults(hang=args.hang_anchor, truncate_row_probability=args.truncate_rows, **common)}
    faults |= {f"tag_{i}": Faults(**common) for i in range(scene.config.n_tags)}
    transport = "socket" if args.socket else "pty"
    if args.all_pans:
        from uwb_env.hardware.emulator import pans_setup

        emu, urls = pans_setup(scene, faults, transport=transport, seed=args.seed)
        print("Emulated DWM1001 devices (115200 8N1), stock PANS firmware (generic TLV mode; two \\r for the shell):")
        for name, url in urls.items():
            print(f"  {name:8s} {url}")
        print("connect_pans(sim, [anchor URLs], [tag URLs]) reads the anchor IDs with 'si'. Ctrl-C stops.", flush=True)
        return _serve(emu, args.duration)
    emu, urls = standard_setup(scene, faults, transport=transport, seed=args.seed, tag_firmware=args.tag_firmware)
    print("Emulated DWM1001 devices (115200 8N1):")
    print(f"  {'anchor':8s} {urls['anchor']:32s} TIERS autocalibration firmware, anchor ID 1 (send b'S')")
    for name, url in urls.items():
        if name != "anchor":
            what = ("TIERS localization tag (send b'S' to start)" if args.tag_firmware == "tiers"
                    else "PANS tag (generic TLV mode; two \\r for the shell)")
            print(f"  {name:8s} {url:32s} {what}")
    from uwb_env.hardware.emulator import emulated_anchor_ids

    if args.tag_firmware == "tiers":
        print("The tags range to TIERS responders with IDs 1-4 (connect(..., tag_firmware='tiers')).")
    else:
        print(f"The tags range to PANS anchors with IDs {', '.join(emulated_anchor_ids())} "
              "(connect(..., pans_anchor_ids=...)).")
    print("Ctrl-C stops.", flush=True)
    return _serve(emu, args.duration)


def _serve(emu, duration: float | None) -> int:
    import time

    try:
        with emu:
            deadline = None if duration is None else time.monotonic() + duration
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    return 0


# name -> (add arguments, handler, help)
COMMANDS = {
    "simulate": (_simulate_args, _simulate, "run the simulator and print a drift/ranging summary"),
    "evaluate": (_evaluate_args, _evaluate, "compare calibration schedulers over held-out seeds"),
    "tune": (_tune_args, _tune, "tune the heuristic schedulers' parameters on validation seeds"),
    "train": (_train_args, _train, "train a scheduler: stable-baselines3 (PPO/A2C/DQN) or Ray RLlib (--backend rllib)"),
    "train-anchor-set": (_train_anchor_set_args, _train_anchor_set,
                         "train the team-size-invariant per-anchor scheduler (one model for any team size)"),
    "emulate": (_emulate_args, _emulate, "serve emulated DWM1001 devices on pseudo-terminals or sockets"),
}


class _DefaultsHelp(argparse.HelpFormatter):
    """Shows each option's default, except flags, empty values and helps that state it."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (not action.option_strings or "default" in text or any(action.default is v for v in (None, True, False))
                or action.default in ([], "")
                or action.default is argparse.SUPPRESS):
            return text
        return f"{text} (default: %(default)s)".strip()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uwb-env",
        description="Mobile UWB localization with periodic anchor autocalibration.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (add_args, _, help_text) in COMMANDS.items():
        add_args(sub.add_parser(name, help=help_text, description=help_text,
                                formatter_class=_DefaultsHelp))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from uwb_env.config import ConfigError

    # A user's mistake is one line naming the argument and exit status 2 (argparse's convention);
    # anything else is a bug and keeps its traceback.
    try:
        return COMMANDS[args.command][1](args)
    except ConfigError as err:
        print(f"uwb-env {args.command}: invalid configuration: {err}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as err:
        # a bad policy spec, count, file or hyperparameter: one clear line, no traceback
        text = err.strerror + f": {err.filename!r}" if isinstance(err, OSError) and err.filename else str(err)
        print(f"uwb-env {args.command}: error: {text}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
