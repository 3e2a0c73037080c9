"""python -m lidar_sim ..."""
from .cli import main

raise SystemExit(main())
