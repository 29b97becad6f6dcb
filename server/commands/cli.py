"""The `scalesteer` command: one entry point, a subcommand per job.

Subcommands load their module only when chosen, so `scalesteer replay` works in an
adapter-only install without warp-lang or FastAPI.
"""

from __future__ import annotations

import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": (
        "server.commands.demo",
        "render server + OpenMM villin simulation, dashboard URL printed",
    ),
    "serve": ("server.commands.serve", "run the render server"),
    "render": ("server.commands.render", "render one structure to an image file"),
    "batch": (
        "server.commands.batch",
        "render a trajectory to an MP4 or PNG zip (on Ray with --engine ray or a cluster)",
    ),
    "replay": ("simulation_adapters.replay", "stream a trajectory file to a render server"),
    "imd": ("simulation_adapters.imd", "bridge an MD engine speaking IMD to a render server"),
    "thesis": ("server.commands.thesis", "regenerate the thesis reproduction report"),
    "schema": ("protocol.schema", "print the protocol's JSON Schema"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: scalesteer COMMAND [options]   (scalesteer COMMAND --help for details)", ""]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"scalesteer: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module_name = COMMANDS[name][0]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        print(
            f"scalesteer {name}: missing dependency ({exc.name}); "
            "install the matching extra, e.g. pip install 'scalesteer[server]'",
            file=sys.stderr,
        )
        return 3
    result: int = module.main(rest)
    return result


if __name__ == "__main__":
    raise SystemExit(main())
