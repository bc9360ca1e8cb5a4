"""python -m services.policy serve|worker [...]  (the same as `viewscale serve` / `viewscale worker`)"""

import argparse

from services.policy.cli import add_policy_commands

if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m services.policy")
    add_policy_commands(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"))
    args = parser.parse_args()
    raise SystemExit(args.func(args))
