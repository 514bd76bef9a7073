"""How the map layers are drawn: one colour per kind of feature (the region, the estimate, the truth), the
same in the report's pictures, in the GeoJSON's own properties and in the QGIS layer styles.

The GeoJSON features carry the simplestyle-spec properties (``stroke``, ``stroke-width``, ``fill``,
``fill-opacity``, ``marker-color``, ``marker-symbol``; geojson.io, GitHub's and many web maps' viewers
draw them); QGIS draws a layer with the style of the ``.qml`` file of the same name beside it
(:func:`qml_text`: a categorized renderer on the features' ``kind``; :func:`posterior_qml_text`: the
posterior GeoTIFF's first band in the pictures' colour ramp, over the decades below its best cell).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from appliance.atomic import write_text_atomic

#: the files of :func:`appliance.outputs.files.write_map_layers`, after the estimate's name: the posteriors
#: and their layer style, the region and its, the points and theirs
MAP_LAYER_SUFFIXES = ("-posterior.tif", "-posterior.qml", "-region.geojson", "-region.qml", "-points.geojson",
                      "-points.qml")


@dataclass(frozen=True)
class KindStyle:
    """How one kind of feature is drawn: ``colour`` as ``#rrggbb``; a polygon's fill opacity (0..1) and
    outline width (px on the web, a tenth of that in mm in QGIS); a point's Maki icon for the web and
    QGIS's simple marker shape."""

    label: str
    colour: str
    stroke_width_px: float = 2.0
    fill_opacity: float = 0.0
    marker_symbol: str = ""
    qgis_marker: str = ""


#: every kind of map feature and how it is drawn (the pictures use the same colours)
KIND_STYLES: dict[str, KindStyle] = {
    "region": KindStyle("95 % region", "#00e5ff", stroke_width_px=2.0, fill_opacity=0.3),
    "estimate": KindStyle("estimate", "#1f3cff", marker_symbol="cross", qgis_marker="cross_fill"),
    "truth": KindStyle("GPS truth", "#32cd32", marker_symbol="star", qgis_marker="star"),
}


def simplestyle(kind: str) -> dict[str, Any]:
    """The simplestyle-spec properties of a feature of ``kind``: a polygon's stroke and fill, a point's
    marker."""
    s = KIND_STYLES[kind]
    if s.marker_symbol:
        return {"marker-color": s.colour, "marker-symbol": s.marker_symbol, "marker-size": "medium"}
    return {"stroke": s.colour, "stroke-width": s.stroke_width_px, "stroke-opacity": 1.0, "fill": s.colour,
            "fill-opacity": s.fill_opacity}


def _rgba(colour: str, alpha: float = 1.0) -> str:
    """``#rrggbb`` as QGIS writes a colour: ``r,g,b,a`` from 0 to 255."""
    r, g, b = (int(colour[i:i + 2], 16) for i in (1, 3, 5))
    return f"{r},{g},{b},{round(alpha * 255)}"


def _symbol_options(s: KindStyle) -> dict[str, str]:
    if s.qgis_marker:
        return {"name": s.qgis_marker, "color": _rgba(s.colour), "outline_color": _rgba(s.colour),
                "outline_style": "solid", "outline_width": "0.6", "outline_width_unit": "MM", "size": "5",
                "size_unit": "MM", "angle": "0", "joinstyle": "miter", "scale_method": "diameter"}
    return {"color": _rgba(s.colour, s.fill_opacity), "style": "solid", "outline_color": _rgba(s.colour),
            "outline_style": "solid", "outline_width": f"{s.stroke_width_px / 4:g}", "outline_width_unit": "MM",
            "joinstyle": "miter"}


def _symbol(parent: ET.Element, name: str, s: KindStyle) -> None:
    """One symbol of one layer: its options both as QGIS 3 writes them now (``Option`` map) and as its
    earlier versions read them (``prop``)."""
    kind = "marker" if s.qgis_marker else "fill"
    symbol = ET.SubElement(parent, "symbol", {"type": kind, "name": name, "alpha": "1", "clip_to_extent": "1",
                                              "force_rhr": "0"})
    layer = ET.SubElement(symbol, "layer", {"class": "SimpleMarker" if s.qgis_marker else "SimpleFill",
                                            "enabled": "1", "locked": "0", "pass": "0"})
    options = _symbol_options(s)
    table = ET.SubElement(layer, "Option", {"type": "Map"})
    for k, v in options.items():
        ET.SubElement(table, "Option", {"type": "QString", "name": k, "value": v})
    for k, v in options.items():
        ET.SubElement(layer, "prop", {"k": k, "v": v})


def qml_text(kinds: list[str]) -> str:
    """A QGIS layer style (``.qml``): a categorized renderer on the ``kind`` property, one category and
    symbol per kind in ``kinds`` (all polygons or all points: one layer holds one geometry type)."""
    root = ET.Element("qgis", {"version": "3.28.0-Firenze", "styleCategories": "Symbology"})
    renderer = ET.SubElement(root, "renderer-v2", {"type": "categorizedSymbol", "attr": "kind", "forceraster": "0",
                                                   "symbollevels": "0", "enableorderby": "0",
                                                   "referencescale": "-1"})
    categories = ET.SubElement(renderer, "categories")
    symbols = ET.SubElement(renderer, "symbols")
    for i, kind in enumerate(kinds):
        s = KIND_STYLES[kind]
        ET.SubElement(categories, "category", {"type": "string", "render": "true", "value": kind, "symbol": str(i),
                                               "label": s.label})
        _symbol(symbols, str(i), s)
    ET.indent(root)
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(root, "unicode") + "\n"


def write_qml(path: str | Path, kinds: list[str]) -> None:
    """The layer style of :func:`qml_text`, written atomically to ``path``."""
    write_text_atomic(Path(path), qml_text(kinds))


#: matplotlib's magma at five even stops: the pictures' posterior ramp
MAGMA = ("#000004", "#51127c", "#b73779", "#fc8961", "#fcfdbf")


def posterior_qml_text(top: float, decades: float) -> str:
    """A QGIS raster style for the posterior GeoTIFF: band 1 (log10 lower posterior) as a pseudocolour
    ramp (:data:`MAGMA`) from ``top - decades`` to ``top`` (the best cell's value); cells below the ramp
    are not drawn, nodata neither."""
    lo = top - decades
    root = ET.Element("qgis", {"version": "3.28.0-Firenze", "styleCategories": "Symbology"})
    pipe = ET.SubElement(root, "pipe")
    renderer = ET.SubElement(pipe, "rasterrenderer", {
        "type": "singlebandpseudocolor", "band": "1", "opacity": "0.8", "alphaBand": "-1", "nodataColor": "",
        "classificationMin": f"{lo:.6f}", "classificationMax": f"{top:.6f}"})
    shader = ET.SubElement(ET.SubElement(renderer, "rastershader"), "colorrampshader", {
        "colorRampType": "INTERPOLATED", "classificationMode": "1", "clip": "1", "labelPrecision": "1",
        "minimumValue": f"{lo:.6f}", "maximumValue": f"{top:.6f}"})
    for i, colour in enumerate(MAGMA):
        value = lo + decades * i / (len(MAGMA) - 1)
        ET.SubElement(shader, "item", {"alpha": "255", "value": f"{value:.6f}", "color": colour,
                                       "label": f"{value - top:+.0f} decades" if i < len(MAGMA) - 1 else "best"})
    ET.indent(root)
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(root, "unicode") + "\n"
