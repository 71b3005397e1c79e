"""Reconstruction: conductivity images from boundary voltages."""

from .one_step import OneStep as OneStep
