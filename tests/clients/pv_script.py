"""pvpython script: open the .vti, .vtp and .pvd, contour, screenshot; print a JSON summary.

Usage: pvpython pv_script.py OUTDIR RESULT.json
"""

import json
import sys

from paraview import servermanager
from paraview.simple import (
    Contour,
    GetActiveViewOrCreate,
    PVDReader,
    ResetCamera,
    SaveScreenshot,
    Show,
    XMLImageDataReader,
    XMLPolyDataReader,
)


def info(source) -> dict:
    data = source.GetDataInformation()
    return {"points": data.GetNumberOfPoints(), "cells": data.GetNumberOfCells(),
            "bounds": list(data.GetBounds())}


def arrays(source, association: str) -> list:
    return sorted(getattr(source, association).keys())


def screenshot(source, path: str, colour_by: tuple | None = None) -> None:
    view = GetActiveViewOrCreate("RenderView")
    display = Show(source, view)
    if colour_by:
        from paraview.simple import ColorBy

        ColorBy(display, colour_by)
    ResetCamera(view)
    SaveScreenshot(path, view, ImageResolution=[640, 480])


def main(out: str, result: str) -> None:
    res = {}
    vti = XMLImageDataReader(FileName=[f"{out}/spheres.vti"])
    vti.UpdatePipeline()
    image = servermanager.Fetch(vti)
    res["vti"] = {**info(vti), "arrays": arrays(vti, "PointData"), "dimensions": list(image.GetDimensions()),
                  "origin": list(image.GetOrigin()), "spacing": list(image.GetSpacing()),
                  "color_components": vti.PointData["color"].GetNumberOfComponents()}
    contour = Contour(Input=vti, ContourBy=["POINTS", "frep"], Isosurfaces=[0.0])
    contour.UpdatePipeline()
    res["contour"] = info(contour)
    screenshot(contour, f"{out}/pv_contour.png")

    vtp = XMLPolyDataReader(FileName=[f"{out}/spheres.vtp"])
    vtp.UpdatePipeline()
    res["vtp"] = {**info(vtp), "point_arrays": arrays(vtp, "PointData"), "cell_arrays": arrays(vtp, "CellData"),
                  "component_range": list(vtp.CellData["component"].GetRange())}

    pvd = PVDReader(FileName=f"{out}/series.pvd")
    pvd.UpdatePipelineInformation()
    res["pvd"] = {"times": list(pvd.TimestepValues), "arrays": arrays(pvd, "PointData")}
    frames = []
    for t in pvd.TimestepValues:
        grown = Contour(Input=pvd, ContourBy=["POINTS", "frep"], Isosurfaces=[0.0])
        grown.UpdatePipeline(t)
        frames.append(info(grown))
    res["pvd"]["contours"] = frames
    with open(result, "w") as f:
        json.dump(res, f)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
