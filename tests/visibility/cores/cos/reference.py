"""The dense reference of the conservative cores' checks lives in ``visibility.ground_truth``
(``dense_reference``, ``boundary_points``, ``cell_around``); re-exported here for the tests that
import it from this path."""

from visibility.ground_truth import boundary_points, cell_around, dense_reference

__all__ = ["boundary_points", "cell_around", "dense_reference"]
