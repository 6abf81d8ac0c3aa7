"""Imaging: MRI label maps / series (``volume``, ``readers``) and real mammograms (``mammogram``)."""
