"""The built-in navigation methods, one file each; importing this package registers them.

* ``point_mass_tracker`` (`PointMassTrackerMethod`): the whole-flight point-mass tracker,
  the Navigator's default;
* ``point_mass_ekf`` (`PointMassEkf`): the EKF started by the point-mass grid;
* ``ekf`` (`EkfMethod`): the TAN EKF with any linearisation and update policy;
* ``ekf_bank`` (`EkfBank`): the Gaussian-sum bank of EKFs;
* ``point_mass`` (`PointMassGrid`): the point-mass grid for the whole flight (also the
  Navigator's acquisition grid).
"""

from neuralmap.tan.methods.ekf import EkfMethod, EkfOptions, PointMassEkf
from neuralmap.tan.methods.ekf_bank import EkfBank, EkfBankOptions
from neuralmap.tan.methods.point_mass import PointMassGrid, PointMassOptions
from neuralmap.tan.methods.tracker import PointMassTrackerMethod, TrackerOptions

__all__ = ["EkfBank", "EkfBankOptions", "EkfMethod", "EkfOptions", "PointMassEkf",
           "PointMassGrid", "PointMassOptions", "PointMassTrackerMethod", "TrackerOptions"]
