"""`usv-deploy`: what an operator runs to put the fleet on boats (also `python -m usv_deploy`).

    usv-deploy render INVENTORY (--vessel ID | --all) --out DIR   each vessel's configuration files
    usv-deploy certs [--out DIR] (--inventory FILE | --vessels ID ...) [--host H ...]
                                                                  a test CA and per-vessel certificates
    usv-deploy router [--config FILE] [--listen ENDPOINT ...]     the shore router (Zenoh, router mode)

docs/deploy.md walks an operator through them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from agent.config import ConfigError
from usv_deploy.inventory import load_inventory, missing_devices, render, render_router
from usv_deploy.router import run_router


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usv-deploy", description="Deploy the fleet's software on boats.")
    commands = parser.add_subparsers(dest="command", required=True)
    render = commands.add_parser("render", help="render each vessel's files from the fleet inventory")
    render.add_argument("inventory", type=Path, help="the fleet inventory YAML, e.g. deploy/fleet.example.yaml")
    which = render.add_mutually_exclusive_group(required=True)
    which.add_argument("--vessel", help="render this vessel only (into --out)")
    which.add_argument("--all", action="store_true", help="every vessel into --out/<id>/ (and the router's)")
    render.add_argument("--out", type=Path, required=True, help="where the files go")
    render.set_defaults(handler=_render)
    certs = commands.add_parser("certs", help="a test CA and certificates for the router, vessels and operator")
    certs.add_argument("--out", type=Path, default=None,
                       help="folder for the keys and certificates (default: the inventory's tls folder)")
    names = certs.add_mutually_exclusive_group(required=True)
    names.add_argument("--inventory", type=Path, help="take the vessel ids (and router address) from it")
    names.add_argument("--vessels", nargs="+", help="vessel ids")
    certs.add_argument("--host", nargs="*", default=[], help="more names or addresses the router is reached at")
    certs.set_defaults(handler=_certs)
    router = commands.add_parser("router", help="the shore router boats connect to as clients")
    router.add_argument("--config", type=Path, default=None, help="Zenoh configuration (JSON5), e.g. a rendered router.json5")
    router.add_argument("--listen", nargs="*", default=[], help="endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    router.set_defaults(handler=_router)
    return parser


UNPROTECTED = ("usv-deploy: warning: inventory {fleet!r} has no TLS: anyone who can reach the fleet network can "
               "publish as any vessel (sensor data, shares, thruster commands on usv/<id>/cmd) and as the operator "
               "(mission/**). Lab use only; on boats use topology 'router' with 'tls' (docs/deploy.md, "
               "docs/reliability.md).")


def _render(args) -> int:
    inventory = load_inventory(args.inventory)
    if inventory.tls is None:
        print(UNPROTECTED.format(fleet=inventory.fleet), file=sys.stderr)
    for line in missing_devices(inventory):
        if args.all or line.startswith(f"vessel {args.vessel} "):
            print(f"usv-deploy: warning: {line}", file=sys.stderr)
    if args.vessel is not None:
        written = render(inventory, args.vessel, args.out)
    else:
        written = [path for v in inventory.vessels for path in render(inventory, v.id, args.out / v.id)]
        if inventory.router is not None:
            router, missing = render_router(inventory, args.out / "router")
            written.append(router)
            if missing:
                print(f"usv-deploy: warning: {', '.join(missing)} not found in {inventory.tls} (the inventory's tls "
                      f"folder): put them in {router.parent / 'certs'} before starting the router", file=sys.stderr)
    for path in written:
        print(path)
    return 0


def _certs(args) -> int:
    # Deferred: certs needs cryptography (the optional 'deploy' extra), which only this command uses.
    from usv_deploy.certs import make_certificates

    hosts = list(args.host)
    out = args.out
    if args.inventory is not None:
        inventory = load_inventory(args.inventory)
        out = out if out is not None or inventory.tls is None else Path(inventory.tls)
        vessels = [v.id for v in inventory.vessels]
        if inventory.router is not None:
            hosts.append(inventory.router.address)
    else:
        vessels = args.vessels
    if out is None:
        print("usv-deploy certs: give --out DIR (or an --inventory with a tls folder)", file=sys.stderr)
        return 2
    made = make_certificates(out, vessels, hosts=hosts or None)
    for name, paths in made.items():
        print(f"{name}: {', '.join(str(p) for p in paths.values())}")
    print("Test certificates: keep ca-key.pem off the boats; for a real fleet use your organisation's CA.")
    return 0


def _router(args) -> int:
    if args.config is None and not args.listen:
        print("usv-deploy router: give --config FILE or --listen ENDPOINT", file=sys.stderr)
        return 2
    if args.config is not None and not args.config.is_file():
        print(f"usv-deploy router: {args.config}: no such file", file=sys.stderr)
        return 2
    return run_router(args.config, args.listen)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except (ConfigError, ValueError, OSError) as error:
        print(f"usv-deploy: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
