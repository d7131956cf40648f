"""GaussianObject's repair stage for warpbags: leave-one-out training pairs, a repairer, pseudo-view supervision."""

from warpbags.repair.network import Repairer, RepairUNet, UNetRepairer, make_repairer, repairer_factory
from warpbags.repair.pairs import NoiseStatistics, RepairPairs, build_pairs
from warpbags.repair.stage import RepairStage

__all__ = ["NoiseStatistics", "RepairPairs", "RepairStage", "RepairUNet", "Repairer", "UNetRepairer", "build_pairs",
           "make_repairer", "repairer_factory"]
