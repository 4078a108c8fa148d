"""Readers for real two-view data. Each returns :mod:`demon_lab.data.sample` ``Sample``s."""

from demon_lab.data.readers.demon_h5 import read_demon_h5_pairs, write_demon_h5
from demon_lab.data.readers.middlebury import middlebury_motorcycle
from demon_lab.data.readers.pair_folder import find_pair_folders, read_pair_folder
from demon_lab.data.readers.tum import read_tum_pairs, write_tum_sequence

__all__ = [
    "find_pair_folders",
    "middlebury_motorcycle",
    "read_demon_h5_pairs",
    "read_pair_folder",
    "read_tum_pairs",
    "write_demon_h5",
    "write_tum_sequence",
]
