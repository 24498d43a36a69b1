"""Runs in a virtual environment with OpenSim's own Python package (``opensim`` from PyPI):
reads our TRC and MOT with OpenSim's file adapters and prints what OpenSim made of them as JSON,
for tools/interop_test.py to compare with poses.jsonl.

    python tools/interop_opensim.py motion.trc motion.mot > opensim.json
"""
import json
import sys

import opensim


def main():
    trc_path, mot_path = sys.argv[1:3]
    trc = opensim.TimeSeriesTableVec3(trc_path)  # OpenSim's TRCFileAdapter
    markers = [[[v[0], v[1], v[2]] for v in (trc.getRowAtIndex(i)[k] for k in range(trc.getNumColumns()))]
               for i in range(trc.getNumRows())]
    mot = opensim.TimeSeriesTable(mot_path)      # OpenSim's STOFileAdapter
    angles = [[mot.getRowAtIndex(i)[k] for k in range(mot.getNumColumns())] for i in range(mot.getNumRows())]
    print(json.dumps({
        "opensim": opensim.__version__,
        "trc": {"labels": list(trc.getColumnLabels()), "units": trc.getTableMetaDataAsString("Units"),
                "rate": float(trc.getTableMetaDataAsString("DataRate")), "times": list(trc.getIndependentColumn()),
                "markers": markers},
        "mot": {"labels": list(mot.getColumnLabels()), "in_degrees": mot.getTableMetaDataAsString("inDegrees"),
                "times": list(mot.getIndependentColumn()), "values": angles},
    }))


main()
