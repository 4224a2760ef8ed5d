"""What people look at: the Rerun log and blueprint, what every viewer draws of a scan, the palette, and the
console's tables."""
