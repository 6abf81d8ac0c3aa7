"""Reports: overlay figures (the paper's Figure 9), tables (Tables 3-4) and the PDF."""
