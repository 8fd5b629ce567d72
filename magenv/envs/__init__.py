"""Gymnasium environments of magenv."""
