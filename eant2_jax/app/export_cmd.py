"""``eant2 export GENOME_FILE --format onnx|sympy|latex``: a genome file's network in a
format other tools read (docs/export.md).

The genome file is read within bounds (`eant2_jax.genomefile.read_text`) and parsed as data;
the output is written whole and never through a link (`eant2_jax.app.outputs`), an existing
file replaced only with ``--force``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["FORMATS", "add_parser", "export"]

# Format -> the default output's suffix (added to the genome file's name).
FORMATS = {"onnx": ".onnx", "sympy": ".sympy.txt", "latex": ".tex"}


def add_parser(sub) -> None:
    """Add the ``export`` command to the subparsers ``sub`` of `parser.build_parser`."""
    p = sub.add_parser(
        "export", help="write a genome file's network as ONNX, sympy equations or LaTeX"
    )
    p.add_argument("genome_file", help="a genome file with a header (e.g. a run's best.genome)")
    p.add_argument("--format", required=True, choices=tuple(FORMATS), help="what to write")
    p.add_argument(
        "--out",
        default=None,
        help="file to write (default: GENOME_FILE.onnx/.sympy.txt/.tex; '-': standard "
        "output, sympy and latex only)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument(
        "--activations",
        metavar="HIDDEN,OUTPUT",
        default=None,
        help="for a file without a header: the activations of hidden and output neurons "
        "(e.g. tanh,identity); a header's must agree",
    )
    p.add_argument(
        "--substitute",
        action="store_true",
        help="sympy/latex: the outputs as expressions of the inputs alone (default: one "
        "equation per neuron)",
    )


def export(args: argparse.Namespace) -> int:
    """Write the export; print where. Errors are one line (ValueError/OSError)."""
    from eant2_jax.genomefile import GenomeFile, read_text

    from .outputs import write_bytes, write_text

    src = Path(args.genome_file)
    spec = GenomeFile.parse(read_text(src), source=str(src))
    if args.activations is not None:
        names = args.activations.split(",")
        if len(names) != 2:
            raise ValueError(f"--activations expects HIDDEN,OUTPUT, got {args.activations!r:.60}")
        spec = spec.with_activations(*names)
    elif not spec.has_header:
        raise ValueError(
            f"{src}: no header naming the activations; pass --activations HIDDEN,OUTPUT "
            "(the run's, e.g. tanh,identity)"
        )
    if args.out == "-" and args.format == "onnx":
        raise ValueError("--out -: ONNX is binary; name a file")
    out = Path(args.out) if args.out else src.with_name(src.name + FORMATS[args.format])
    try:
        if args.format == "onnx":
            from eant2_jax.export_onnx import to_onnx

            write_bytes(out, to_onnx(spec).SerializeToString(), overwrite=args.force)
        else:
            from eant2_jax.export_sympy import to_sympy

            net = to_sympy(spec)
            if args.format == "latex":
                text = net.latex(substitute=args.substitute) + "\n"
            elif args.substitute:
                text = "".join(f"y{k} = {e}\n" for k, e in enumerate(net.outputs))
            else:
                text = net.text()
            if args.out == "-":
                sys.stdout.write(text)
                return 0
            write_text(out, text, overwrite=args.force)
    except ImportError as e:  # the export extra is missing: one line
        raise ValueError(str(e)) from None
    print(f"{args.format}: {out}")
    return 0
