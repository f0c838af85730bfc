"""`metarig export`: fabrication drawings (SVG and DXF) of a design file, 1:1 in millimetres."""

import argparse
import logging
import sys
from pathlib import Path

from design_engine.design.export import (ExportError, design_name, fabrication_drawing, write_dxf,
                                         write_svg)
from design_engine.physics.geometry import InvalidDesignError

log = logging.getLogger("metarig.export")


def _check_output(path: Path, kind: str) -> None:
    if path.is_dir():
        raise ExportError(f"cannot write {kind} file {path}: it is a directory")
    parent = path.parent
    if not parent.is_dir():
        raise ExportError(f"cannot write {kind} file {path}: folder {parent} does not exist")


class _Parser(argparse.ArgumentParser):
    """argparse with usage mistakes reported as one line, `<prog>: error: <message>`."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def export_main(argv: list[str] | None = None) -> int:
    """Write fabrication drawings of a design: unit outlines (cut), ligament positions (hinges),
    a scale bar and the design's name, 1:1 in mm (SVG and/or DXF)."""
    p = _Parser(prog="metarig export", description=export_main.__doc__)
    p.add_argument("design", type=Path, help="design file (JSON, metarig-design/1)")
    p.add_argument("--svg", type=Path, help="SVG file to write (1 user unit = 1 mm)")
    p.add_argument("--dxf", type=Path, help="DXF file to write (ASCII R2010, mm)")
    p.add_argument("--name", help="text written on the drawing (default: the design file's "
                   "'name' or 'task', else its file name)")
    p.add_argument("--scale-bar", type=float, default=10.0, metavar="MM",
                   help="length of the scale bar, mm (default 10)")
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already reported in one line
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    logging.basicConfig(format="%(message)s")  # root stays at WARNING: no JAX start-up chatter
    log.setLevel(logging.INFO)

    from design_engine.design.design_io import load_design

    try:
        if args.svg is None and args.dxf is None:
            raise ExportError("nothing to write: give --svg FILE and/or --dxf FILE")
        if args.svg and args.dxf and args.svg.resolve() == args.dxf.resolve():
            raise ExportError(f"--svg and --dxf name the same file {args.svg}")
        for path, kind in ((args.svg, "SVG"), (args.dxf, "DXF")):
            if path is not None:
                _check_output(path, kind)
        lattice, x = load_design(args.design)
        name = args.name if args.name is not None else design_name(args.design)
        drawing = fabrication_drawing(lattice, x, name, args.scale_bar)
        written = []
        for path, kind, writer in ((args.svg, "SVG", write_svg), (args.dxf, "DXF", write_dxf)):
            if path is None:
                continue
            try:
                written.append(writer(path, drawing))
            except OSError as exc:
                reason = exc.strerror or exc
                raise ExportError(f"cannot write {kind} file {path}: {reason}") from None
    except (ExportError, InvalidDesignError) as exc:
        print(f"metarig export: error: {exc}", file=sys.stderr)
        return 2
    w, h = drawing.size_mm
    ux0, uy0, ux1, uy1 = drawing.units_extent_mm
    log.info("%s: %d units (%d vertices each), %d ligaments; units span %.2f x %.2f mm, "
             "page %.2f x %.2f mm, scale bar %g mm", name, drawing.units_mm.shape[0],
             drawing.units_mm.shape[1], drawing.ligaments_mm.shape[0], ux1 - ux0, uy1 - uy0, w, h,
             drawing.scale_bar_mm)
    log.info("wrote %s", ", ".join(str(f) for f in written))
    return 0

