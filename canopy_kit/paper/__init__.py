"""The paper's own data (Abedi et al. 2025): Table I as shipped data, its consistency
check and the statistics it implies; and the paper's experiments re-run on simulated
orchards (:mod:`canopy_kit.paper.experiments`, imported on use: it pulls in the pipeline).
"""

from canopy_kit.paper.consistency import Table1Check, check_table1
from canopy_kit.paper.summary import Table1Summary, summarise_table1
from canopy_kit.paper.table1 import default_table1_path, load_table1, read_table1_text

__all__ = [
    "Table1Check",
    "Table1Summary",
    "check_table1",
    "default_table1_path",
    "load_table1",
    "read_table1_text",
    "summarise_table1",
]
