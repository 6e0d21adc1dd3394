"""The simulator: a physically faithful flight written as a real project folder (layer 9, docs/ARCHITECTURE.md §1).

Scene (``scene``, ``scene_objects``, ``texture``), flight plans (``flight_plan``), true flight (``flight``), sensors (``imu``,
``gnss``, ``scanner``, ``camera``), writers through the real file formats (``writers``),
named scenarios (``scenarios``) and the consistency check of a written project (``verify``);
see §6. It sits beside ``workflows`` in the same layer: neither imports the other, they meet
only in project folders on disk. It may import any lower layer; only ``demo`` and ``cli``
import it, so production code never depends on the simulator.
"""
