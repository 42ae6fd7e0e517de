"""Checks of whole BOP datasets (``cosy validate``): every problem collected as one line."""

from .dataset import ValidationReport, check_symmetries, validate_dataset

__all__ = ["ValidationReport", "check_symmetries", "validate_dataset"]
