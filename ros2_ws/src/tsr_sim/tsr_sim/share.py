"""Installed packages' share/ directories, found through the ament index of the sourced
workspace: where files looked up by name (plant variants, presets, shipped models) live."""

#: What a lookup by name says when there is no share directory to look in.
NOT_SOURCED = 'package not found: is the workspace sourced?'


def share_directory(package):
    """share/<package> of the sourced workspace, or None where there is none: no
    ament_index_python, AMENT_PREFIX_PATH unset (its OSError), the package not installed."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return get_package_share_directory(package)
    except (ImportError, LookupError, OSError):
        return None
