"""Datasets: containers, CSV and rosbag2 readers/writers (interchangeable everywhere)."""
from pathlib import Path

from .bag_io import MEASUREMENT_TOPIC, read_bag, validate_batch, write_bag
from .csv_io import read_csv, write_csv
from .dataset import Dataset, DataError, Trajectory, concat_datasets


def is_csv_path(path) -> bool:
    """CSV paths end in .csv; anything else is a bag directory."""
    return Path(path).suffix.lower() == ".csv"


def read_dataset(path, **kwargs) -> Dataset:
    """Read a CSV file or a rosbag2 directory, by what the path is."""
    path = Path(path)
    if is_csv_path(path):
        return read_csv(path, **kwargs)
    if path.is_dir():
        return read_bag(path, **kwargs)
    if not path.exists():
        raise DataError(f"{path}: No such file or directory")
    raise DataError(f"{path}: neither a .csv file nor a rosbag2 directory")


def write_dataset(dataset: Dataset, path, **kwargs) -> Path:
    """Write a CSV (path ending .csv, plus JSON sidecar) or a rosbag2 directory (mcap)."""
    return write_csv(dataset, path, **kwargs) if is_csv_path(path) else write_bag(dataset, path, **kwargs)


__all__ = ["Dataset", "DataError", "Trajectory", "concat_datasets", "read_csv", "write_csv", "read_bag", "write_bag",
           "read_dataset", "write_dataset", "validate_batch", "MEASUREMENT_TOPIC", "is_csv_path"]
