"""NGM weights shipped with mergesvc, written by `mergesvc solver train`: do not edit.

TRAINING says how they were trained; SHAPES names each parameter; DATA holds their
float32 values (little-endian, in SHAPES order) in base64 (core/solvers/ngm.py).
"""

TRAINING = {
    'command': 'mergesvc solver train --seed 0',
    'date': '2026-11-26T13:13:57+00:00',
    'torch': '2.13.0+cpu',
    'best_epoch': 10,
    'val_accuracy': 0.8955,
    'val_accuracy_node_only': 0.8147,
    'elapsed_s': 464.8,
}

SHAPES = {
    'gnn_layer_0.n_func.0.weight': (16, 1),
    'gnn_layer_0.n_func.0.bias': (16,),
    'gnn_layer_0.n_func.2.weight': (16, 16),
    'gnn_layer_0.n_func.2.bias': (16,),
    'gnn_layer_0.n_self_func.0.weight': (16, 1),
    'gnn_layer_0.n_self_func.0.bias': (16,),
    'gnn_layer_0.n_self_func.2.weight': (16, 16),
    'gnn_layer_0.n_self_func.2.bias': (16,),
    'gnn_layer_0.classifier.weight': (1, 16),
    'gnn_layer_0.classifier.bias': (1,),
    'gnn_layer_1.n_func.0.weight': (16, 17),
    'gnn_layer_1.n_func.0.bias': (16,),
    'gnn_layer_1.n_func.2.weight': (16, 16),
    'gnn_layer_1.n_func.2.bias': (16,),
    'gnn_layer_1.n_self_func.0.weight': (16, 17),
    'gnn_layer_1.n_self_func.0.bias': (16,),
    'gnn_layer_1.n_self_func.2.weight': (16, 16),
    'gnn_layer_1.n_self_func.2.bias': (16,),
    'gnn_layer_1.classifier.weight': (1, 16),
    'gnn_layer_1.classifier.bias': (1,),
    'gnn_layer_2.n_func.0.weight': (16, 17),
    'gnn_layer_2.n_func.0.bias': (16,),
    'gnn_layer_2.n_func.2.weight': (16, 16),
    'gnn_layer_2.n_func.2.bias': (16,),
    'gnn_layer_2.n_self_func.0.weight': (16, 17),
    'gnn_layer_2.n_self_func.0.bias': (16,),
    'gnn_layer_2.n_self_func.2.weight': (16, 16),
    'gnn_layer_2.n_self_func.2.bias': (16,),
    'gnn_layer_2.classifier.weight': (1, 16),
    'gnn_layer_2.classifier.bias': (1,),
    'classifier.weight': (1, 17),
    'classifier.bias': (1,),
}

DATA = (
    "FVlkvV0aBT/63Wy/YF1Mvziltb5Qc1k+QE+ivORlSz9wv7W9sjGxPpJ/nr5wSEm+n111v/Bh777oDtO+FFEnvQqe/j"
    "5jPg0/0eMSvwdBtL4gttw+bv85P0i9Ur5Tsi4/QA0lvjAvOrvaFnc/znttv/wkIr+2BP4+3JPHvlC/UT/2FWy+KTAd"
    "vhraMr6csHu+8alxvmbcJD68duQ9nx2uPUBqVzzzshu+Cm18vZ4Gb77MbEO+vngkviaFIT6+6p49BEr7vSj7Cb0f92"
    "s+skKrPoWQtT2LuMY8/qQrPs+eOL740D49mRI5vuYmM77SPgS+ItNBPiosBz5qpBe+/eSPPbep2j0Nsx69guORuwuO"
    "2TymIfw8qjtiPpZHRb4cO8e9mDjJPd/FVz5TySY+IuJhPssMqTy8/oe+kGa8PGHNPr5PtG2+Nc5lPmYCgT7BTXW+JK"
    "3ZPWTRI724gii93yDlvYzkxD0VUxu+4vy2PRZ2AT4B7FE+Swg9Pkpffb5lxiS+pJ4hPaHQn7uWs0e+Zm4Jvi4uLz48"
    "v8U9sD7fvfAc8b143XO+dYs9vWdSkb6id0W+v9j8u/wdwzz0rdG9AJCEPR01Ob7lAm0+0G8vPmThV753/CS+oVvFuB"
    "hnFT0B+I09XOzIPSkmND3fYWO+1EXyPVaRdb6avke+PCuAvdheHr5cHbO9utJRvgDSWb344lo9dsYmvkA0UrwAQjc+"
    "8IjSvICs4zvArbC8ED1PPWDGIj66fnI+BpMiPsQMcz5gHZS8ZvhlvkC68r3OTy4+AGvUutx8/r0CLUS+AJRvvuwQWL"
    "5wtE+9VmQMPnRnCj4C5Xa+LrAfPopSSL7we1i9HJrPvfyDK7wkOFe9vJGYviQCk74Grjc9LYqDPLiW6L39yq49Ompm"
    "vndVVr2wDKI+ONfQvXBDMD7y/dC9rgdnvoXqRj5EITq9vUcDvhS2TD5U306+sMLbPA4yjb0W0DY+ZtdZPcwE9j0b0p"
    "I9AD92vVBaV70A91K+TLYKPiZCSz4cKh4+rzF+viHNC72QdjS+iOwMvjrEgb74odo8xI0Yvk4JRr2gTyw8Q+kDPt7r"
    "lr5Evy++PKYUvtYuMz7MC7i9uBEOPi5wAj536AU9AbDuPRmOCTzuK4I+X+EcvQA+5rqqAQA9mD5IvmiXGb7yK4g+hs"
    "FPvkfoPj1khlQ/EPS4PX9YKD2p4Fe+8P0RPhyPF76XkUK92sBGvh5RwbyANjM7Wn1pPoCr/zxO+4Y+2cP/PcbYIb54"
    "Ags+JFcYv5z/2L0GFp498A6pPfIOQD4o0qS9ANTROXrLAz5ak3e+QhU5PjCxU74A0GE74BguvQrUBr7YVwc98rBTPu"
    "iqlb1W/Be+hFu9vbrgpb58xfA8IOX1vdDWKr6s7fK9EsSGPSSSBz63St092La5PU0LK77Qnsa9mEKXPd5wUj50NYs9"
    "HEDyvaNjQb5CCnK+sDtdPaipD75QPmS++npgPtA/Jr7Q++i8SK+SPeB9Ajz6QSy+LO5OvpgNTD4wvyY9RmJUPqikq7"
    "34z5Y9z9MEvs+JZbxmozy+bF6uPcQq3LtSCUC9wExmvVjOHb7gEls+lpFPvqWJ1zwfJFK9+yT0veD0Nz102k++QO9r"
    "Pdtyfz4+dBC/cGGfPvZu7z728tY+c0bIvYG4L7+04Fe+9VDPPizRur5Tkdg+CWlCP7hI076Jqps9YjoNP5SLlD14zT"
    "g9JDK5Po5mLr9aUAQ9QaoZPxzsbj/bJDo/MrICPph3zj7cE/m+GGdjvwuRTb8UvI0/5LoGP7OJEb9bGc0+PT+HPiBT"
    "JjrWmPo+BTGMPoTdjDzBZgy9LQTmPefcnD3AXJu9/iVmPq2rzT6kBls+hy8bvlmMCT43RLO8vemDPsZdfb0jQwo/1y"
    "WNvWAnnD1daJ+9o1Y8PuoThjy4r4c+WeoovrqNfL4zV5y+oOMrPmE5Mz7nxJU+wapQPsmxMr5HDii+cr9PPVa8bT3R"
    "B0E+WNVFvmsvK74gaYa+zVEmvgeNTj5CmlE+qnbUPpqoZT5CiFs+HwTKvfcH7T0w50Y+yRyovdYBAj/ftvE9VFWLvN"
    "gpY74DPKY9CwmpPg+nUj5SmZC+VqUPvqE5ir74TcO7fSCDPmnz072ca6e+t5XEPe/zPj7xHo68QMCYvTrRhj5Pp6s9"
    "TuCkvqd5E7zAnr28YDrNvVzpDz6l9Ri9YyVEPeS+3zxxlY290mj/vYi8EL6BluO96a2wPjFo9D1bqDQ+7lohvBx/kb"
    "1Qb4g+Y3rBPpdqxD3g92m+5dVtvi08hb6vv9w82wQbPm4HXb62a+Y93/C0Pq6bO75XRx+90AVtPd9nMT6PblS+saqS"
    "vXSt1748guy9wL54vmp+bT4c3aw+v7yxvi0VgT5neWA9vNYXPmC1oz1aQZO+6iHYPqlgXD6f7Jg+ol9nPWLUkb5E0F"
    "w9Y4WJPYDM8j3FiTC8qv6hPBOhor7uBQG+zlb0PcGwSr4QNaM9LGwJPhinDj0MSSu+WntGvuT1nb0gv+A9eoR8Pho1"
    "Ez6wn+a8AISzPfAme75iplq+POfuPZYAEb4sUvY9RMstvnf6ez79C72+KyH/Pbk5ATzffYw+dyebPp1enD4KwRs9lE"
    "yevY17hb593MK7IL49PuEP0b0GvkU+m5YSPfrP770eqku+VN3OPmVeqD7IaCW+Ap0FPqgMZb39qyi9LqWSPqb4Cb5u"
    "Iqk+XkVwPi2fQb7aZ7M9nTpbPWpbNT4H1Iq9mgSWPsSm/L1+kIk9iAyyvU8TuD0RCmo+FHemPRJB2z24+Xa9n+LLvc"
    "rBYr558gS+UeZavfZyVz4sPJM71Z5ivcwP+L2SnEc+WPpBPocgeb6z9YK+1AtCvgAInrqZmvK9TpAnvubOE76Cr/a7"
    "9MEFvmq8ZTrDguW9qcgzvp1fzT0KgEo+zaEmvZGiqz02Nh+9dtxVPvbVsL7P5c6+0EKaPvj3Ib7EdpE+RRuQPUsd8b"
    "1XQ4W9fV1fPh2W4jzm3kG+skslPvAqjryPnzY+7I0QvhO3Tz4F+wq+x58PvmHIZj7mqgA+R93YPhmblj5YF4i+8/Mi"
    "vtmlID7Lulg+jP1HvR5obb79X8U+oT6PPitxsL3i0MK+2eGGvuGT67ypcKm82EYBvm5tCj8SRZA+Z+jgvUjmzz0uvQ"
    "w++auPvqLKKr42K5U+nDGaPfT8OD2Beqa+1GGbPnDggz4gsj8+MPVXvjfZjrygrkC+sdudPpLLJb42bwO+u8jYPYw4"
    "gr6tcII8iKeOvj01yT3d982+gqO5Pgd07r6oroQ+czXFPuNEDD5vcoO+Jfe3PhjJnT0iIye+1d3IPkfAKD7aUay+Hi"
    "u0vcpHrb2ZbbI+lCwQPe4kPb7CCTY9Cv5HPmX0GT7eTyw+3j+FPLDniD4v1Ok89ulmvOTtpb7Bg8O9hcdTPglL174B"
    "6EK//rEkPsCtJT4gmXy9jCSSPngdvL1Kq4s+u1y1vVhuOT0sF3w+rL+IPUP0kj5atbC8WOQrvmDWdLvdTgY+k/4kvj"
    "3RZr+o+lQ+UUOXvUEdTT2FyCk+ZJRgvbv3gzzY/60+1VVuPU/PtT3ecy++usuePmjro77NLqa9NYp9PRq3DD6WWTk/"
    "8yeGP1D9+b3swYy9x3W/PYDlyr2i6wk+xEdiviSn571g3Lu9WgR3PdEkET4nqvC9jeBivn66aD0g1Nq7t9nnPNVBQ7"
    "6rk409dEbnPi4bNz2J0de8ScKfPfkeoz1P/sg8DS6HPunvoD04L309IkZ6vi/KlD6FtEm+/cANPQ0DgT5jhrg+Akk2"
    "P4jrkT9H1C8+Wny/vY1lybz+gQ6/4wHgPrMn8r0uflc+tZhpPr3JhD6QyW0+Q/3JPnEk3b1HqQA+Kkt3PSvATrxXRf"
    "M+EN5zP101ob3lP4Y+r9kjvKdkmrwi8IQ+E98LvFK+DT4udU29F9+7Psc4lT37L2K9yGxPPp6Ijb2Ul5m9Hy37PX18"
    "gr2q6kG/2xMBPuak6D3qrBg+hak0vtB1Qbs7Tx++7vtJvgP+ibx9U6K89cyXPfU9qDzIGrK9erCTvmO6Kz6GdRi+dS"
    "GxPtK8Qz+RqNE9EvmDvqHhNT47JlM9F0tYvsK4qL1zbiw+2Vhovg8D4L3abX097GKCvionvz1tKLc9MS/ePSgZR75k"
    "wmQ+OzY4vufnWT5Rf4a+2E97vjGKGD77T4W7eGOlvCSiJ75oRwa+IBbUvd2liL4QLIm8HWxMPMlFBr3Ohkg9cYtNPk"
    "qvDz1hEfO9jYr4vXpwMr5Ij0C+/8xlvVdPXL1HsdE9hmMFvqDOOj6SszG+Hi/WvAXzVT4+KFs+LHwGvldGmjzZT8k8"
    "fOLovSR6lr2yxyc89m1lvnWosrz7sFc94jkXvkuOHz7fa6C9xulSPVhYTz7nJVu9gJ2sPRDttL3xAqS9bBXSvcSASb"
    "1AY/S9SHziuQObgz4sBlo+2oE/PrLqqL5JRD8+g7pwvsWlsz6nkoU+U9aOu2A9SbsW2KQ+8pcOPEC/pD7CxIY+pTqU"
    "PvoQID9kEUU/y12gPVtnaj6C6Oy6mKQkPiZBAr25JWo+PWsjvrD4Nr5JFe495nS5vUH18by7Nxm9oSUsPp+rib62fx"
    "c+96sOP+Gbsb237yo+wsaFPtq1dD1tALG9G/3vPVV4N72gjGs+hP5JPhCfs71SsZ2+pJZWPt0SP72BSYk9ECm8PhYJ"
    "uj6zJhM/5PN5PxE6gzsJKhy+WyWnvTjqPD7x50g+ILsoPoKvcD6Hc7a9jZdxPoNMkD7tr8u8awutPr9Qfz4iQIk+Q3"
    "qivApZOL5vLyS/EODdPT2RYT78FIU9SVkTPlUUgj4G+lE+zHqMPnuiuj0RXI692VZfvpBLyb0p8KS9zEu2vTmpIj4E"
    "D949XormPSkpB72BiwE+gRuWPRp/YL5oWnq+3slkPUIoVr1egMs9HKx/vipBbL5o/Bw+0r8jPvzEkL4InZw8yX55vq"
    "Xdzz2DZiq9F4VFPou0kb53Lom++AQBPut94T3L4dY9r7kCPhifV77aSzk+oLNxvmjDZD07g4u+WbYRvgv4BjuKVBe+"
    "COIKPkR18L36p4y+vwSsPdg2372AdDy+HFvFPCcsUr6CnWm+7i4ZPr1GQD5U8BY8+rOtvZiuBT4WvKc8jpFUvbhaXD"
    "2hpg4++zSVvnyQfr7OiqO8ZdAFPtfBZL5wUvo82PYzPqTbnT3Iml09+Gp/PjJy1z1i5Ve+ECD5vNrOiT3SxGE+7LN+"
    "vkISpj1wor69enOYvruSB7yyXgu+A157vAw1Jr6+pUC+YMatvHT+q72I1pw9IJOwPD+yDz6Yq6O8sKOkvbxlLT6A01"
    "88QDJAPbirpL0AMms6QONEvZAdrrwspke+AIXJush9VL5AS1y9JF0UPnoCMr6ojiy+aAl6vdr4v71uE208PVnNu5ch"
    "qz08012++E5Mve2sEz5RoSk+xNZHvXQgFL6U1cQ9Vo7VPcgdT769/T++EWiBPW4k/by19hi/NbPNvgKniT5nkni8Wl"
    "ujPizIyD6zgDm+Z9kVPjsLUr0GKYc8unoZvNmhC75Go509VSNTvooVkD5OYr2+RClGPuNPRr2j4W69isWRvdCEFT5z"
    "t2A+ps0VPm2UMr4KAsk9iuCdvQhK4r3kkiI+M9SgPk4ta76+POY9aiepPp20vj5GUMM+g29TvuNOGr7zPAc+ieXrO6"
    "is0D6tLIC+fl4kvoUbc72muVy+MmOmPbGs0T3CghI8uM+DvT+nmT6ZOEC+iAJhPqG5oL5ZVd6++wfjvTM1KT7L1v08"
    "BQFFPFamO744Pns9wNnkvMA4zT3JYxs+RLAaPXmaZr2ExJu7Omskv+2yGr+as0M/SkoRvdrTDT94gdI+0iQLv/g4Kj"
    "8KEkK+SOrdPC39Q73W6948r1/4PpDJQj45oAw/LRQFv3TW7T1MzUi+MvBZvliCnD2AyXA77Nnuvbjpdr60Nsa9/AGr"
    "PTj0bL72sXi+4OoBPWhsOL7MRmC+PETFvWjdJL2xyTm/kAUmv6o5nj7MhTW+r74uPlt6Fz5QZRW/XkzIPm/vH75Yxi"
    "G+70elPYgQxT3GZAM/PTbzvUHfdT1Q8Kq+AMmlOqg8Qz4Y/36+sNGRvPx74j2Q+Qy+hBUCvuBu9z2gS3W+iKRyPRYx"
    "Rr7kfv497uNavthjHT6EVnK+Yi9Xvs/EkLzxcDM+lBFuvvBh5L1B4Uo+4LgrvW9hpz1z8YS+pAOhvUoBAr7c0lc+HI"
    "DUPQbMOr5Xipc8qV/GvDEm/72VemG+4+YBvgErcz77z2a+dn5ovjj2nb3KxCa9zSvuPS0drT2fmqK9bow5vgkEHjx4"
    "G869wMJTPl4xeb76ozm+VLA1vqBIfb05N2A+9nVXPjmyQb42+CY9Ut76PfG+yT0CKFA+2bjdO5yuL75EI+09gHNmva"
    "nR9j3/J6e9PG2PPkdSxj4ekW0+7WNbvtemHb7/tsC9aL8XvobodD5i2nS8HB0evlLJz73uLgm+herXPTcDUr7g8WC+"
    "YjBuvv4b4z2nbgE+Rp4TviYjIj06iog+aBawPR+8bz1mZOQ8AJOHPEVLAT5Bm/i9Caf/PeLIbj5IDR2+2M5xPtnQLz"
    "72QSq98ICoOzHIaD13ZLq+aMYAPjp6AbsTVjc+ZfaJvqdVML6OaAA9OdTSPRK9Xr5d5yO+YBWdvvKNEL4HDk2+fxw1"
    "PiHoDL0uwgc+lw+5PgcpAj4GXnO+UdkxPjIZsz0AtG0+9FlbvhcZOT7u2UI+CaVlvkozNj2MzYE+It84vqG8Hj5elM"
    "w9iJuIPWBLkD7UHdQ9AzQOPrdIljoNXmI+N/5Fvq2TBb3nfb28naotvXkOcT7qUQE+nyNCPjXEhD7cwyW+1C9iu58W"
    "ZT1ce6Y9UmgHPvfTAr7jW9O9QRc6PgWwsL3YVDm+s1YTPuvJIT4ejMq9E5tGvd1BN74slWm+AUGMPc/E4b0dQDA+Kq"
    "Jmvv5QCb395j68wUj/Pbn8SD6J1Hs+ZjvXPTZgNr078Ya+HpAPvqgA9r2HKKU+DbHXPBP13bwmck6+qHMmPl1e9D1J"
    "J4u+D02rvfgYbT4DVDg+ROhpvkWVMT3ZChe9rJctvlwSaL6VWCM+PE/svA15uL2LNYC9l3UHvjwek71aMVW+Ids5Pj"
    "nUyj3FgPq944ipvRTY3j1977e9tlWoPZ3w8DzNgtK9On21PYBGuDz+SV8+KE/ZvaerY72ehjI+hYSRvnt6+jsWQgU+"
    "ivMUviKOfT4hWEY+V0y9Pjl6VD2Mxus9KAJFvnDEM76t2/A8wtlVvSfM+DzWBv89LfJ7vtSErT2w3NS8BCYJPRemiz"
    "2q4Bq+MpuXvkHXpj3c8SW+IQxNPdMarb48TkS9IonIvUSANj6kqYy92ytTPSVpOb6DapO9QLU8PoEyob38qAq+MRUQ"
    "vgqPKT7Tnqo9JSipvXG2j71uR5W+eiw2PpnypT2cnWc+1i6jPt5BRj7thio+gNMPvry9jD0ecqa+2O2UPtpn/7vfj2"
    "09lDDmvoayTL49beY9c8jKPLxaf74Pb3U++C0tvVb7LD4ypeu9tWQJPvSzJT1aIGc+sOmMPrMYgD6+mcQ9SxRQPlju"
    "db6f1mq9xwzXPTRttz3K45i77dirPRdD/bzpRQ2+lKcOPnYDiD2owzQ+VHdWvGeEmL2TBEC8QQ2fPcGjdD4AaAK7AS"
    "fgvDInf7zyrZA94YSpvSH0pr6lKb8+DHxBvQR8PbzqjVA5dvgbvoZYbDtq5iQ8TPzhunj7hD398d68baIwvkSLhz4n"
    "J00+PK/LPdFBqTz4ukM+aLCYvoV/Zb5CITe9BCeivV+yST73MBi+jXWvPGKeQr3hS32+bC9nvel5Ur4sVCA+B4FePa"
    "0KTT4Rf9m8FoWMPYjkIj7Y44Q+3Z4vPs0cC76is6q+Ng8rvrOMib6d/08+fPSrPd7Sqz6mwD0+Lg4Xvft0Pb7910M+"
    "gB8+Pm1m4z1Fghu+iTODPQGF5j1zqSI+bGPVPPpuFj7qiVm+m0NPvsjdDD7kXAy7/rZevvPFdD40PEG8BKY+PlJ0lr"
    "5OREc+pnUCPr2gOL6FFdi9zUuwvdc6Yz5rcYW9qAA6Pv5CGj5YVUK9v4PMPIxpar4r3Si9Iw4Pvi9zBL3oHSQ+7Drp"
    "O1Xpp70c2oc+03CfPSlQi72ANzG9TjkPPpf4Rz51qIK+VKeEvXrOmj0MYLm99IJuPgEFFD3WNYo+vkIEPglhXb04uL"
    "u9QXo4vQ8fQ7wQeuI9Y6gLPkQBiz5cWSC+6R/4PfIegT6OP7q9oD1LPtph1ztvsgm+wHmmvZzYij6M5jW+7ACpvO66"
    "nj55rx8+AKy/vE6Ber3DGNC9l4eNvlYgk75sz1a+GBfQPEB1Rz2ko/K9jNyOvgg/7D3abQ++yjkpPbVgZL7Oaoa+Nb"
    "CwPaiFbr4VbiS+Uu4/Pva8Fb5kEtW9lMGPvezb2j2g7Se+VQLnO1k0rD2EIRS9wrnePOK8Vb6Ueec9qnOaPdsvlj3H"
    "TVq+/8vRuva7Sj6id4y9jfj1vFG2jD0GhSy+QCyOvKRYnj5M22G9GRY0vhsYDr5Dljc+hRusO4PuX777iDc+UG0HPh"
    "exjb2gQlE8CLdZvZtVAD3gkRE8IOoavoi4PT1JRKW8BJgsvAPL+b3I+hg9sVpqvnQMmT2xvt49u0LJvWI9QL4xaag9"
    "LdoyPYPjkb63CQC+aV9gPsttVj5A4A0+51k+PkD38T2JBDA+AGOAPmP0Cb3vYQ69PxkOPkK/y71kkya+gp/dvSZCIT"
    "5pVJ4+ao/xPWDDAD0YxPC8yAprvkT2a743DUG+uSWAPiLtIj6Qjnm+FUSYPdHanr2XHzy+QHrFPT1AfLpZMAi+Lj9M"
    "vkwBhT0OqEI+D/Yzu8CVAL55Yak9WJcyPWofYL5vSGO+rZSTPABoHj55zAe+StMAPUiLHr52jK8+66xJPvqWzz266M"
    "U9emKdPUEAd74A3g67brnfPduufz20LbE+GpyJPRBfpL5IZ1q+eOAyvh+sXD5w1+W9eq+fvtSLH73CsUu+3+Z+vuqC"
    "Aj6/tZK+jHTxPa8GsD3lfgC97pOLPZhjVr4W4zc+oVodPqVser1yerA+bm+CvsSpq707HIg9QQT8va+4Lj18V8O9y0"
    "6EvjQdS76nkfw989gyvl5bKb2/Ltk93S1MPpYCLD5YCRC+LANgvX4UCT5Jh9+8NfdwPoCTxT3ZGdc9IBtbvhvHNz6U"
    "Peu93wtXvYjAw7xXcMu8gX0gPeFiiT6RbZW86e8ovaMgir7Vl1493A91PpPgaD5P7Ys+ocnuPR2EHr2xh/k9JlMGvu"
    "z2dj5fJwY+2bZ5vn6XmD6vfuy9hQW7PO7Tkr35YFm+It2zPddJXb7u2Gi+JEOLvrdK9rtA/V4+rGySPjzmir1OUPo9"
    "UbAAvpi/sr3mqQe+fhD2PMp/ez6iVJK9WbDXPbAmDL7RBpu9AYccPhToIL6to1e9SzFtPjMCqj24ZSW+PBg8vq4e/L"
    "1xfOm9EUmKPe9mvL2xeio+xUQIvvsc6b3h17Q9rL2lPnqyij4jYiA9bhiJPc81wr18iy8+Z0jXvdkIL70OQtO+VYdw"
    "vlAdRz5iS4a9UHx/PkdZbD7Hq04+2QZHPb+mCz4mr3g9taQSPSfw4zzCHpe9QjtkOUzdMb3gclW+qlbfvLoKiL21JI"
    "U9vtBbvgHGFL79GTi+QsbjPW17hb5xPUI9xM9FPYGpAT4PezU8WRGxPRn0Ej6+EZc755ROPa0qa76Wve+9GvCpPBii"
    "k7wfbAa+AzSUvjAV4b2VrS89P08hPoeUkr7+fYQ9e807vs70V77bLWC+G5x5vDyl1rzqrvu9yIRnPtXwaD6v4Xq+Oh"
    "cMPnEJw738FWO+4ovWvEeLkD3B7Z+9qb96vg1Nnz441oo+LL6LPrzRa75aoKQ9TKSCvq6cHz75l8E8g9AbPi9zaL7e"
    "S8893gT1PcR+Ab77Cw4+8M79vW1VlD4xqj8+JK3hPin64bucCIq9lP9qvQekEz6QsOw9xAyePUplaj7YPpo8T78nvm"
    "nra7oWvnK9F+kevuqpUj0vLeu9FUHaPS2Du723ue4+YJBfvsmiEr6RDHO+H4x6PUEoP770tKA924IsvqgXH74uwv29"
    "GhUVPcM1ZD54o2g+KRuWvK9Dc74BGqS9g029vSVMU73lfIc9y4FiPXqfyT2ShsI9mfFdvR1WpjwZWhA9wno4vgi7U7"
    "7zeua9kSt9vrM0ET2/i2Q9FLxmvvOEGz5YlaS+hK9jPnxVEj5sfIG9m72NPsQVyj0ry8g+hznxvYQm4b0CORa+juVP"
    "PpyTED4fUpY9h65Jvr9C/z3JPkS+Va3Kvbh1Kr5O5tG+09QGPnLaFj7ubTE9JWvNOginq7tIEi0+oSRQvlnfVr4Z+s"
    "a+IdCQvUs5P76BfmO+mACqvfFX+j2I2Ro+VT1bPvfu1z6vpO69gCnjuKTtYz3aPHU+56gcvQBtjL1P9/S9l9UJPtqi"
    "1r6zW+O9ATU+PhhOtT2NfK084/Qqvni0WT6YKB2+jIKAvL2ZLr7CNuq9LOhCvugkDr7/N2K+2ylPvVqP5T2gZ0m+tf"
    "00vfyVsr0gkO89zPk4PjTbA73yJxi+BtQ+vou0J77xjKE919BaPlA9bD6Q6/K9B+gjPuTNjL6shP097JaOPqAEKb5B"
    "cZe+7O4WPuhrd70/TIO+ocMFPqwjuj13YSg+cghOPKis2j687qI+hafIPd/OL70S8go+qJCBPWevvLyWNAY8kyf2PZ"
    "0Rwb5jLDo+QRjgvU/hQjx0Q2K+9ckCPrPihz4af1Y9ddoQPkHswD7M+zu8eEGCvlh2Bb7wdIK+20TOO3474b0uJ9U9"
    "kjrGvYKJJz6Jzm++ct95vkhXyT0llDm9h0G3PkemQzyf9xA+vqjDvSziOj444gE97/I0vrzoRj7H5Aa9xTR5vPBPoL"
    "sp7j4+1NOvPq296D1XvK89GQQkPqo3P70NBty9WNq5vHM5/r2l+So+wHaaPTif5Lzm2wg9G54DPU2Yyj7IhWQ+znIB"
    "vu+VTz0CBDg+THMBPl/D1rz2Ay8+McupPddE/z6GW3W+pErCvcA8LL4gW/i94AxJPVYhHD4+l0G+ZIEmPlzWVT5QXv"
    "y9QLoyPbZsA77AU1s9+F/tvbxzx73iXiu+W+Uuvv9cgT4DkK08G5VQPTyYkL3C5Fg+g18YPagVz73eTA6+AQ+ivigu"
    "oT7cuje+VrLpvA9oLT2b8+o9zte3Pk6aHb5+0pA+o3FKvimFpz3UnRc9/KmnvB+ttj4kJVg+QRjQPUrN1L0on4c+K2"
    "RFPgrRXj3LEgI9jyr+PKTv6T5l1YQ9gR7FPDh9JL5RDZ69QbF3PoGnOT1CPP49SFrHPTs97L3iH8i9eZLcPH56Jj4M"
    "OFY+bhmRPld9aD5zuLk9VVNTvfy1oj0h/yG+GlUAPqax5r2Hjgw+w3rMPrb+Wr4SLY8+mSnsPRyku72Bx4o+kXFSvl"
    "y5s72aZdq902wnPkDhNz3OJy69DOFyvi7dYr3GYz8+Z/5pPrZ2bz5orBQ9MVSvPW/oHb4k7DE+i0GGvshw070+KGE9"
    "4MtQPlfPSj6EOOm9Je2rPaLtYb676AS9mVeUPWdHujvnXwU++nUcPikLOL6g0qW+aCGyPqWKgzxoJom9Cix1PijXQD"
    "7sVZ4+6ETVvUgh070Sx2I9a29oveTywj07bHi+4ntlvLIoQz6WUZ48atOePZ+1qD0wA+G9d+7XvZAI3Dxe3Pm7H4cg"
    "PthJBz3364k80Oq4vLAhLb7A1Bq9F4kRvrtztD0ioCm+/xEfPuC8XT3IroO+65ERPuwqfb4aWWe93tUfvgA7XL5w6s"
    "o8BKMBvmzUFD59T1q+llwuPkFXEz5Izls+GO6VvStXeL5RxXC+IY4dPh3cBb4ZmjC9HTIZvkfSZz1pptG+U40pPjUD"
    "Vb6WuGo+NVTevY5F3L3O3Xy9h62EPEi7Pb2ZIL6+XqbpPZm9SD7yJfY8soB6Pj+g4Dz9ase9DRhzvsq+X75wwEG+qs"
    "OcvUbP4T1gaRO+IhgqvCCJiD6AVye+ns9ZO2pxmj7XznY+X0IgPog0QDxO+4+9nrYvPnsXsb6bK4K9zZyMPt/8hT2C"
    "9+S9z82JPi7dpz0YnKA+rlZevhSj5z2/igY+lSg8PYRD0L33QlY+HUZhPs/7zD1jjJs+gM+0O5Ha/j242l+9Lfwpvt"
    "LInD16rEM9fPHCPUB547yJYFW9l8YevQV/QD1r0le+cptuvkzWmD16ih++kEisvMFG2z1JlvI9IlZZPv92tz2AEQk+"
    "Cl8kPffATT7svLs9KWtrPtYNu74sZsc8OhY9vjDZ2r2PXZ4+wXIivjeZ7z0eSic+cC0XvrzsKD7PpeA9QJ9lPbqgdD"
    "7HDnW+GQ7fPYx2vj1YnFq+iRmRPJRbBr7Hb0i9Ru7AO7oSDL7djE4+sdAzPjLncb17BHu+8Q1EvRysErypEgQ+ZbP/"
    "O+56GD1qpUA9m64uvl4NGr625H2+KqP5uq7iKz3Lnk69bNdOPhzoor3Xkxy++0HvPVaoFT1f/XE9+9OyPlYUAD36yT"
    "0+k7IePd67Vz4XhpY+V8qVunm6ib3w/zM+0sbpPXcjbr5P2SM91hEIPZY6Ij4a2i89llMzPjaiPj1CoO27zwp/vRAp"
    "GT4EdKK+mCdhviB9Fz1rEp48jbccv/4gdz67Z4y+cYRSvifqY71dHMI+4n3LPWaTJL1BGMg9p1b/PdGHf74aQYg+76"
    "4wPqjsqz5ufae9rLjJvZdyDL6l18M+Cr5CvbqxRz7MuyS+0aOKvf5uQT3yyo48VXQYvub4eL4ebvs9nsehvVjzhb6b"
    "RE8+3JGyPazKDL4FSlW+NXJQPj1f/7wArzW+7g/cPW6vpb1R5Iy7iUMhvsqMd75Dvxa+AW0PvdHlRr4XBmQ+MWDYvN"
    "RXxb0Z4hk+SD6NvTcuI75hXps8i2mXvib/sz2trQO91F46PXKDa75SDmo+3fY4u6ZThry5xum9OQO0vVFN/j3o0I28"
    "admqPGoUj715Ry0+CDeAPv9HwD4BB+a98+GfPrU8Xb4wvBC+Kk9Zvd3rAj4QD8k9qxmxvINrIL6NYju+7xhvPk6Lhb"
    "26Rwa9MjUYvhZA9r0bMlo9cjXRPcBcxL2G07a95bxEPsLQ/72FSzm+b/0avXlSbD5N5Gc8oQm0vHh2or3n18w9C7sU"
    "vnuPEz4CQtq7Es2ZvXS3LrxNuE2+hHfKPXW8mT1EGnC+O95wvhz2tL0P1s89KYz0vZsvZj45vPm9TFdgvnJ/2j2+Fx"
    "a+G5ocvT7tmr2n3528QWlYvvrKY75/htU9GyThvPLQFb4idcq7265ivkLZgz0CqYE+n02kPkN8Ib6ducA9PwUOPjHp"
    "oD6/jPG9yFSLPtcMtL0cahQ+QOkzvnGY6D5T1HK90guHPLZEDD6bvJw+sIZIvjTpOj0A+TE9GEc9PrmHTT6F6hU+Xu"
    "ghvmfk4L07mAw85o0evr9CFT4VgSe9mUMHvwYKJT5yA7++SzgKvoZ4ID7dCYG+4m4vPSTVw70cG7093ccVPnTlYj4f"
    "WKa9s4BrPflFHj6NJ+s+2nQ0vSD9iryx2ys9sN++PZsXrr03UiC+qZ1XvspQ373zH8w9A10HvkkENr4eSwg+4IBJPp"
    "Qx6r1ErsY8VLp9PdnRhT75cRK+lqr0Pci00D53wIg+B5lJvTwbZb10VwW9k0U/PuetYL2O8lK+ij1fPrYpBj3slDw9"
    "1OtMPT3hJ7657xs+6XuEPrTo0L03rL88PBYkP3N7YT5Kh/g+68k0PNETiTxVXXm+NoDePL+hSj26tt066nkbvlLdij"
    "5aL2m9ysFGPSgdyr31sjg+SvmBPhDodD4oSVe9PvWQPq5O8j0iP6+87DSCvoeDWr72YIu+j6qGPsftbj6aJlU+u0c9"
    "PQ1kCz2BxaY+stL7vaHU9r1x/l6+MEGuPTyl3D04ciw+cAELvuO7DD1hSg6+EFArvtfctz0nDde+Xa0wPlhlUL79/1"
    "K+ngHavchLdL5wxjk+VsFRPklstzzXAzS9nRU0Prt9h71LQ8U906g5vsYlOj5qiWC+AKU9vcAUfjyEn6i9NES7vdRA"
    "Xb7Ar2E8UIrovHIuXz6sj6i9wt1FPqDnQTxQCOa9uIZzvdBo6LwxMB49DzKWPMw9kblDhJA+L4VAPRVelr3Lzxw+oL"
    "lcPXrHJD30SAY+r56+PgU3ob7dFAw+8MMbviWPgz1ELsm9SOgZPrcJGj7lFm++OPtbPVSGMD7w9zI9wmaivab/RD6A"
    "4fI7GGl/vW2iub1YWQY90UTpvKiOGrwufpU8Ra+BPQZgT74wKH890qEcPlDe6jxQ77q8ohpEPpKpX74Msum9VGvnvY"
    "YyXT7Ym3e+sB3LPAL8d74gsQa8cNe+PZB3b71OAYs+vl6tvXztF74hBzI8J0v2PQA0ArptJek9ygYivph12j2uXRE+"
    "OmOlPflXa73/XO68vNVIvjYTWb7gl368UFcAvSoWPj5y4zk+iJQtPkyD6r0w+Ei+siBwvmBMuT1UrWa+3o1/vphgAb"
    "5MJFi+4MXJvfYpIb4+VgO+rGJzPg0QPLyqMlk+yzQ6vp5qvj2K6zS9CclcvhDDhL6OQjE+Pb+IvUSYeb6F29s+KPV5"
    "vhhLNL6t5KG+Q2IzvmF+jL7sqGc+qJODPj7zUT6kYoK+R428vfn5Zb4g6G4+MPKHvUqH67w8wJ+9r9/bunt5oT4Zlf"
    "U9JhxzPXsdF742Vqg9TqI+vm1RYD4lFGi+uw9yPliDD77/YP289cRBPeANa77Mjv49MPRDvmIZGD25JNy9r6gSPn07"
    "0j6jXzI+J3P3PPCq/b0SyDw+JTLIPT04Bz6EqAq+YjBPPkKysD6w+Rw+DFEHPdBv7T3biH2+7rS+PpU0zrzMb00+wo"
    "U2vo19XL0gcPC9TFoLPgzcJL50lIG9pCMBPlBpzjyA/XC+WI9+vqzr+L3uHGw+vbxPvk+r5j2H8h0+ADnUvUga4r36"
    "LDi+oTOuPPhzST2xAXE+FJL0vYZCnz3H4la9B7UYPmA/cz3Faes8sOlMPcN2ZL7j6rk+GtY1vK712b3AZg+/BZs9vo"
    "DT/jvcPea9LrYAvt+dTT1AWbe8eBC0PcxuMz70Y+u9AP77vRjFTb3eN8+9qAoAvnKuDL5AiV29VgD4PHrXbD78kT0+"
    "gunavPAOgbz33zE8oDQnvPBiBr3ID7A9GkhQvji2Wb4Au4Q6Dw0EvgQ//b28Y5K+cA3qPeBQgb3eigm+8zKHveUWmD"
    "1BaKO+jBcxPi07yjyh+qo93/dVO95DJ75VrqY9ak9BPrdnUj5Xx8+8bfTvvVXghr27Ciw+S6w4vgI+fz4cDHK+ZUyl"
    "vKkiWr6a+Be+UGZLvvg5cb6YOSQ+A9wtPWL+jb5R2Ik9pyiHvYboKD7Q0Ya+OPT8vTxIIj7iJ08+UO6aPKw+pD1jO5"
    "g+LyV0vQ78aT5cWHQ+cMSBvlOjpz1gNYW+9CWNvQUctDyXRN69BXxrPtWduTzjh5q9FsfkPQkYOz5JS1M+Mw9GPnF4"
    "Qz6EyEI+HjhUPRJKRT457y0+GeaJvnl2m742bGm+y3muvZod1L4/vEo+SXcbvvPFcD4DqZA+I+uMvg=="
)
