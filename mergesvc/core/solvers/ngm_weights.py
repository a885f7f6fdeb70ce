"""NGM weights shipped with mergesvc, written by `mergesvc solver train`: do not edit.

TRAINING says how they were trained; SHAPES names each parameter; DATA holds their
float32 values (little-endian, in SHAPES order) in base64 (core/solvers/ngm.py).
"""

TRAINING = {
    'command': 'mergesvc solver train --seed 0',
    'date': '2026-11-26T15:33:28+00:00',
    'torch': '2.13.0+cpu',
    'best_epoch': 9,
    'val_accuracy': 0.9124,
    'val_accuracy_node_only': 0.8295,
    'elapsed_s': 859.2,
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
    "UjbiPHrIHz8Ws1K/VE5Bv+qOhr4UJXw+QE+ivLJXZD9wv7W94BCiPml7Lr5wSEm+tnxzvxlYL7/oDtO+Wi/dPTlFDT"
    "/lDhc/jI0tv+MI1b6E7gU/BBU6P0i9Ur6kETc/QA0lvueFlzw0c34/znttv7p4Ir+QK4C+3JPHvtHiWz8lMHe+XKsm"
    "vhraMr52wm++1sCLvq5yGz68duQ9y8acPUBqVzyK+yW+V4uOvZ4Gb74a+ji+xvkDviaFIT5dYIs9yBHjvSDLE7xAui"
    "M+gn9+PiQ0yz3IVQo9/qQrPsC7Fr740D49bHpGvhhuMb7SPgS+jKrnPfjnzT1qpBe+yK2aPe1H3j1IPiK9QGQcPG6d"
    "XDySJxM9RoRlPpZHRb4dJci9mDjJPd2bVD6yaSQ+IuJhPruMSD0SKoe+kGa8PB1iOr6db4G+hZ9PPvCmQj5asoW+6q"
    "HaPH++fr24gii9y9EIvozkxD00oRe+N/6RPRZ2AT5cQzc+CQOaPUpffb6/yDq+0NhLPTzUzjqWs0e+6GgTvifN/T2h"
    "ltg9sD7fvQyG47143XO+GXc2vUFxkL6id0W+ILBhvLUFrTz0rdG99x+ZPU/aML7xNY4+0G8vPmThV758Hum+4PKVPB"
    "hnFT014vM9XOzIPZ/o0z17T66+1EXyPVaRdb6guxe+PCuAvWi0Ir5cHbO9utJRvgDSWb344lo9dsYmvkA0UrwAQjc+"
    "8IjSvICs4zvArbC8ED1PPWDGIj66fnI+BpMiPsQMcz5gHZS8ZvhlvkC68r3OTy4+AGvUutx8/r0CLUS+AJRvvuwQWL"
    "5wtE+9VmQMPnRnCj4C5Xa+LrAfPopSSL7we1i9HJrPvfcjB73ZN8K8urhlvv5ufr5bgYe9l83IPLiW6L1WpvM9Ompm"
    "vsOCLDzpYWE+ONfQvWtiZT59kAM+rgdnvi1gNT7eFDi9/MMCvhS2TD5U306+sMLbPJkqjL0W0DY+oOZbPcwE9j0/2Z"
    "M9AD92vVBaV70A91K+TLYKPiZCSz68rR4+lDx8vn+qHb2QdjS+iOwMvjNDh75U+Ng8xI0YvkTyWb2gTyw8aIH0PZOU"
    "kr5Evy++PKYUvtYuMz7MC7i92sYQPrM4hj7rWlw+AO3zujzcBL2zP089bHjlPQA+5rprQVw+mD5IvoB0YD1gg5w+hs"
    "FPvgdJm7xxYag+EPS4PVwWKj6jQkq+ZbUdPghYNr40v469mlwAvtqJsryANjM74bVzPoCr/zzSJog+D7ASPsbYIb7I"
    "PeA9PxkVvpz/2L3hU6g98A6pPfIOQD4o0qS9ANTROXrLAz5ak3e+QhU5PjCxU74A0GE74BguvQrUBr7YVwc98rBTPu"
    "iqlb1W/Be+hFu9vcMOpL6zKiU9IOX1vdDWKr6w+P6943mXPSSSBz4aF/Y92La5PXJjG77zEwW+mEKXPd5wUj50NYs9"
    "HEDyvcSzPr5CCnK+sDtdPaipD75QPmS++npgPtA/Jr7Q++i8SK+SPeB9Ajz6QSy+LO5OvpgNTD4wvyY9RmJUPqikq7"
    "34z5Y96dQPvmAnNryRbTq+noqDPWN2+jobbIi9wExmvVjOHb75Y0E+Cw5Pvt716TxJLIo9IWzwveD0Nz0KKEy+QO9r"
    "PcpUlj7zNhy/uJWhPhyC9T4tUO0+y//8vZBtIL8KJyK+fxjXPizRur700bc+/JJLP/Qh6r5qgjs9sTMMP/xPPT2Hh3"
    "Q9TMmJPnTUJ79ZcY89LsEYP6VHYj+S6lM/ceB5PgF1xz7cE/m+8Vhjv65MN797vY0/GkcdPyKeFL8J0c0+9zSXPlwx"
    "5Luv09Q+EoubPmQiOz2TZpm8V/YIPkzrvz0hQzq9/iVmPiwTZz4DD3U+UCJNvjczHD6WHgc79DKRPhdzub10Ouw+Vb"
    "P/PV3PRD2Y1da99RYDPhHu9z0V4qU+4dNFvrqNfL4tFDa+JbUZPgjZLz6ty2s+XlI1PhRiaL7khhi+o2prvfLCUry+"
    "Ykw+NOJCvr4LU77gzfO+2iKZvq7uVD5CmlE+cwebPhkmgj4v0yk+hkQGvgdHKT66aTg+5gFFvG+60j7zdAI9iu5FPS"
    "K+BL5MGDE++vQOP+hz7j6DVka+VqUPvvCaib6Z05G9oS7FPpgVhzo3z8e+PqRGPne0Cj5FBIU7uLvxvTY7Uj4Lqp89"
    "g3BavsiiXT6tCSs+S8TsvVzpDz7WdBG+uHkgvXiUQT5muly8QAw1voQK3L2v/7u9sgWpPUuysbzlJ04+lL6VPDyHCr"
    "3Trv0+COoXPwO8+D3g92m+BW13vefij74Q3gw+D6EnPignjr73Kgg+hJmJPjCRVz1YhaA8ymgDvbCyqD3cmpK+ifxT"
    "vvZGHb8KfVG+wL54vrR3XT1uXZc+BiUCv/akHT4D3g49+XdWPW3Q4T1atJ2+MfqnPlf2cj4EaqE+trbGPEeT5r4Yq2"
    "C9SZ6yPYDM8j3OKaa9xpYtPVCKuL6oDiG+2mIiPsVgWb4QNaM9LGwJPhinDj0MSSu+WntGvuT1nb0gv+A9eoR8Pho1"
    "Ez6wn+a8AISzPfAme75iplq+POfuPZYAEb4sUvY9ydtrvieTTD5agLa+KMiGPcIdNr3HDIA+YNXUPsSUtj4rno+8lE"
    "yeve4sF76aDpO9AiVPPrf1D74NafU91BbBu5j7sr2VxG2+uBq9Pv/ztD6+Lwi+eSYNPnsNDL71jqu9Ie2hPqb4Cb4v"
    "fS8+CSBxPmN4Jr5cALQ9LsJlPdhtPz6dzNW9NqraPSXlHb1jAyg9dvYIvhKthT2uesE+Si7DPc57cT24+Xa95wdEPQ"
    "CCdL7DPuK9f/jBvRzQRj7X81m9xsFtvcwP+L1r+kQ+LCU/PhH5e77njYK+1AtCvgAInrqQQPi9TpAnvmJrFr6YPym8"
    "9MEFvlyF0boDIeu9sko2vlbcBj5OjQg+RimsvPLV4z0yPIq8ktxYPhhz+r6bcfC+AbqmPvj3Ib5I70o+JIbkPS1zDr"
    "7oiEG9mpKQPvVoOT2McIG+MhINvpQurD1qces9tMVGvrdjKz5yIZO+yNurvklyLD7mqgA+vNyPPnePUD62r0W+Aylu"
    "vn6YcD2eVBM+lbpovR5obb4m8Nc+YYiKPiNmgb2NmpG+HpF5vr7kOr1XtvG72EYBvrPocz4/VDg+idAYvs6cFz4WEW"
    "E9HH15vnq1Fb79PG8+9QIjPW7XEz4evXW+hOujPqkKLz5voB8+MPVXvrvqZr0q3je+4TeLPqpOKL4Gtuy9d01wPSWe"
    "LL4Hq6o8rpKpvpDp+T3JQym/+bsoPnBu+b67h5o+EYvmPgXF4j0wlru+PM7KPh7O3jwMzj6+xPvwPqe2ZD5LLYu+uD"
    "UGvtrSPr5hGEU+F1eBvU80dr5ZKRK9USkGPl7eEj0TVV490v0hO1ABxD3Kg6e987z0vbf0fb5V4VK+Ra6pPepvJb4l"
    "oVs8LRgbPs7FRz5tdfG9Z3+lPqz8Jr6rT5M+eRsWvjF33bu9cbM9YNqyPD1xgj4IKVa+RW6svprHPL0bUKY9yKSvvf"
    "rTPb+Y5FU+QZwEvQGWiD3FCUU+x/gZvpwSTr0BvLQ+NDTDPWmQPD53pQu+jQWjPsbjib5qVIy9H/enPbu+Kz5oyAc/"
    "w+V2P3if5b2Gkpq9Jbu+PX6VBb72SBs+Z2NpvpCOzL1YB7a9upE+PYTHSj6OY+i9gixwvl7mWz0HhSW7GVsJPc0+Xr"
    "7AS6Y9V1TCPsguLj3FN6u94tsvPkHIGL6B3E67u0ZBPhQzNj1r+p89T9KIvk7WXD4aeTK+Ss0cvfhAPj6C8aA+ZXfQ"
    "Pqz6fD+Yzoc96jkZvmMg0L0fNZS+xzhUPpd+i77l6wY++tAFPjpqCD6EwHk+UzOQPhw27r1aaJ+9PcVhvfw1db0OCC"
    "A/gz5VP48Ilr3Pelo+A/+CPPA7GTxdnk4+RePcPSyrKz6QMtK8BM2WPqG5l7ydF0G9AyouPr0dEr0YJiW9uTcOPp/L"
    "YD4L/uy+d6oRPmwdKz7Y1jE+ZbQfvtbmsrwj+WG+KGUwvo8Xmzw1tPM9yFX6PSTfPj3qQl69+kRlvpAkSD6hB9+9J3"
    "AGPm6DOj87f7E9pVeOvqYTJD41neI8/aBmvnXN4r0fGho+PEB7vmIdA767wco8gOmKvtZorD2bao49Ih27PdblW76O"
    "mz0+0/NLvt7nUz43rXi+dIl+viWKGD7Wps88Lzw2PDbgJ77QrAq+v/iVvRTwcb6XKqy8HfoWPXYSlbtdJTg9DShUPl"
    "RcHz2WBNi90dUivv8fUb4uYHC+dQyevZBU0rxSMY49/1gqvtmlBz4QaE2+oHulvVuZLz6dICI+tsQovoj287wnxAg7"
    "PVdUvmLuGr4QnE07pxRwvnL56LzSHRs9TygCvgz7HT7WIK+9GqhKPV9xPj6Q9gy+D7upPfIoBr68rKu9mzvjvV9/Pr"
    "1iDh6+vclgPKhHzj0/Ufg90ZTFPDT8B7zhrqm9eUWzvq4HMT4aKtI9x4wuvvpNCL6N7h8+FX4wvm51FD1uzqY9xosQ"
    "Pu+F9j7KLs0+jkmqPq20jz6LtFA+Of+ZPbEpDz2Ol4s+/QG5PX5pyj2hCI0+TUpXvlvhfz6QA3w9mLK3PoV/u7ot4q"
    "I+VVACPzBnIT5CpEU+2NyMPr+Vwz2obWC9686xvbpi973Sfoc+kb99PlI4srxpt5G+TH50PsDFDj2uTk49FQfNPgHd"
    "0j474co+3OBTP1YfsTu1bQq+b6KbvaGxjT5ycDQ+km+PPrv4dj6gAsi93Fn1PUBEgT4mzha9zleePglHST43RpA+44"
    "rFu2Kb3jy7aS6/TCUOvdx2cD40NO89kskJPrBqkD5gwzA+7f6GPnLhAD4kkrm9SeFSvkd9FL4Cyai99NkovjRpiz62"
    "DCw+pjYOPrBbdz0q0bI+/dLUPBp/YL6kt0m+DioNPbNRXT2b4v28HKx/vipBbL5o/Bw+0r8jPlhZpr4qoqw9fxeGvg"
    "IXWD4kqaA9sMpSPhP7kL7ycXa+hfAFPmBIYz7Uxuo9gtYMPhifV77aSzk+oLNxvmjDZD09/jC++TASvhXs7Tvr7gy+"
    "HRBZvCY8GT6J21O+TOH5PYxnT730xV++an41Pg4jJ743f2O+7i4ZPsPIFD4HqUw9oj8Cvld1lj7JpjE+XcAHPrhaXD"
    "3R0js+y3NZvnyQfr560Fy8EsZAPkt6Sb6ga2E92PYzPqTbnT3Iml09+Gp/PurGJj5JDj6+JVrMvDXkqj3SxGE+ufRI"
    "v0xXlD5gppS9maCrveCNnj7aioy+p5tUPgw1Jr6Bez++YMatvCWto72ikeQ+vbWsvR29nj4iuG6+sKOkvbxlLT6A01"
    "88QDJAPbirpL0AMms6QONEvZAdrrwspke+AIXJush9VL5AS1y9JF0UPnoCMr6ojiy+aAl6vfB6xr3oewQ8rzpNvCe0"
    "mz1TQ2W+XBFXveBH6z1RXiY+5oVJvXQgFL7ux1w96vPDPWwOO77PFUe+Au1qPdg8Ub1IuVq+5hkIv+Cdsz7dBdi8qi"
    "fJPn4tKD+n9jy+yLFBPp4tML2iCD28mufwPIzMGL5FwqE+VfFQvi1MvD6i682+OSs+PmkaD75aVFu+Hm/RPaIEEL2f"
    "CB8+Q9hDPX9vmL7k6iE+WNVAvQhK4r3iYRA+ZLU6PkG1kb6lcMG9PCgYPqlvqD2+TYU+C9UnvmSGHr4PlRw+qKowvZ"
    "v6ED6ft0W+fl4kvlAN8Lwhw16+TeOmPfmmtD0d76y83Gskvi2iczwQfyK+Ph8qPk6Nfr7mO3W+2uD3vbgcUT60JjO9"
    "6aWGPVamO74YuLo9wNnkvMA4zT1QzDQ+cocYPZ2ohL02Iri9g+wUvnFI8b6FIgY/7jglvTKTBD+RPvU+7KpBvlwirz"
    "5PEkW+3s0vPEpEqrwPdLg8IbQBP1zvpj4gcgI/07K/vnTW7T1MzUi+MvBZvliCnD2AyXA77Nnuvbjpdr60Nsa9/AGr"
    "PTj0bL72sXi+4OoBPWhsOL7MRmC+PETFvWjdJL1pKVC+C7ypvqRpyj0RXS2+XJl3Pfh0fD3MLKK+ggBBPsfqE76OrE"
    "C+fGfyPUV10j3c1bU+/HYdvdnYZ70v0mi+AMmlOqg8Qz4Y/36+sNGRvPx74j2Q+Qy+hBUCvuBu9z2gS3W+iKRyPRYx"
    "Rr7kfv497uNavthjHT6EVnK+Yi9XvgBzcTt2eBw+VT+EvvBh5L2gDjM+4LgrvQEJcz1cjZG+pAOhvUoBAr7c0lc+HI"
    "DUPQbMOr6EqIS7k1JDvXUUFr7cxNq9a5/5veIsyD4j+mS+1un2vTj2nb2hJ0W9mPTRPUxviL2cPum9JsFevnYclD14"
    "G869TvCEPl4xeb7J9U++uDsRvrtDcb2JYGw+uo5sPui8Fr4P4ce8ii0pPlsmHz56Uig+Ih5PvZnV8r0kwYE8NzQOvi"
    "znLz6UElW9ORBBPmD76j6F72Y+QwVivm1IJL7TX829j2Aevk1Mbj72ea+8s74kvjII3b3uLgm+U6fKPRWhWL5/kWe+"
    "99F0vs/Y1T0emvU9vz8aviRy4j3qQVg+skMiPro6I702jxQ9ZUf8uq7ZNj4oTIa93OZ3PoInSz4P93q9DQq2PkE7wz"
    "4AHcU6rkw4PaTgSD6OsRK/X1UhPlh/yT3Mi2I+7EMOvgePS76225m8n7ojPiQyIr4Id4i+Qc0Gvmwa+b0abVy+fIPo"
    "PDaptjxCw0k+7BCPPhCQcT6i07O+SAsgPlONhTwgBHM+gMmDvsXiED4+wJo9aLq2vsIUdj1NBn0+x4Cevr0UNj7J99"
    "496DZzvW6dRD7qa8k96rx1vVp1iLzb7w4+k9Q1vindKb6IphG9wpx1PCtGhT7Sjg8++k2hPhcvID4JMxm+WvkFPve0"
    "WD6pI8Q92zghPvT+A74ZSz++7jMPPjGUr7y7UVu+z9dsPtkYwj6Yj/e8ZcC2vYkjdr66cwO+pjhCPrt4OL6Mu48+/+"
    "K+vep0pL34I029NY0KPaKDtz4gwD8+VpcQPnDw4L2w2yi+rV94vuqTJ77E/4M+b22VvFjoML6HAs69ciDGPeei6Ty0"
    "S9u+DioavvfZPT4CIio9dNQsvkWVMT3ZChe9rJctvlwSaL6VWCM+PE/svA15uL2LNYC9l3UHvjwek71aMVW+Ids5Pj"
    "nUyj3FgPq944ipvRTY3j1977e9vlPlPeg2pT2GBeO92/vgPaIJaz2jR1c+JFeFvXVym7yFSxg+OzuBvhImTT1A3b49"
    "rrQxvt6Siz6raGU+vGGnPrUpDT4I1E4+/oCXvSAQdr3v6L09SwmwO2JJWj6lKIE+JIMXvm2nZz7CfAg++mwEPuYMmj"
    "4FwEY9xa4yvvxIYD7TckG+6DYkvdsKG74bS7G8WIBIPW9Jhz0seZY9fJzDPNeoAD2dmBE+sOkNPkPONb7QcpM98RqT"
    "vmaI7DwId4w+0agtPTfcnT0HeHi+lCsOPnxJPbsHuNw9dYE0PoU6MT5RICk+3dyDvhGoy7yINIO+M9GEPrRQ0b2lsr"
    "87qPCfvmRVqb7DMMM8kMpVu1Ts67xHK2w+5mMBvjaOGD7F2Dm+heD5PRvf7b37Pmo+GwOOPs6iNT54FIe9vT5PPlFc"
    "0b48Zje+RcrsPVU9OD3CRQW+SxQpPhsGG75H1I6+Qph2vOasAT79mMk9yYsdvtXchb5IXki+WxMHvYZEAz61J8m9Za"
    "IuvrQ/Kr7M/6u8lraJvispW76XM00+AgJAvmbbKr7l0vW9WrLEvvqfuL2+VZe9JODlvXvipL1wzlY8MXIBv71t/j1v"
    "OkM+SQAlPkjT+L0rXZY9Adadvm64rb0Ov4O9/GmvvZZaMT6tMoG9f6yfvDwKub30y2O+AHnlO+l5Ur58chU+HQQuPi"
    "pGgD7PLs29N1L9vGwwETx4jgU+AzUjPnh9BL7TYJK+V/9ovp3vLr5ebuU9fPSrPWC3UT6mwD0+r0aSvbardr6u5Sg+"
    "kCgvPtJ1IT3s1wu+izczPueOmz2gRik+Y36cPIqSfD4/kH2+SvaFvtQyij6kNLQ9/rZeviEZfD4/rrS9urBxPqP497"
    "0l220+XFT0vceiTL6feAG+xIO9vWlVFD7hLri9Gmp5PriWYr1lhN09ujlOO4xpar7uNfS95zyVvoYj273pdw8+UYPW"
    "vfoRsr2mgmE+NzsQPkhKfL3oBSe+v2liPu2Uhj74082+m/bCPsLCO70MYLm9AzRqPnUV471bP0c+g9KlPaSGrbxTUe"
    "W9lpTwvfECmT0QeuI9JpVlu+DwUT5WKbe9EolxPSaNiz5dcjS9oD1LPvxTe71/tYG+hloyvhatGTwCe+G9Dr5EPQvJ"
    "ID6/gjM+AKy/vMdjprsrZpC98d+BvkIJNr6mfgu+bl8HPkB1Rz0D3pi92LajvjkyKD7wFEG+b2qvPcCmVr6LtOy91k"
    "pePaiFbr6MF0a+bUQDPsrCFL5kshu+SmKrvezb2j2g7Se+pGRJvPSOlz17s0q91rnePPQcbb6Ueec9rXOaPdg4OzzG"
    "rVO+CjKWPbFD4j2fMq29Ar36PTHGhLxkzYO9QCyOvMaTez7iT5I7Z9E5vkk9EL7pzBk+RZvNvacGmr7qaDM+UG0HPq"
    "rtlb1DLpO8cjVqvcmy3zx7BbO8IOoavoi4PT10Qca8cNFuvFIIAb6cL4M9bgNPvnQMmT2GuQo+Zs2fvWDcRr4+WPK8"
    "amAvOvIBor6IDHW+vSllPnGteT5A4A0+ghUAPllcbbwApvw9nvTBPYAPRjw61E697p2DPPEqYjxkkya+b2iTviyitT"
    "11sCA+ClRMPirI1Dw15q48yAprvok2I75maZ6+G3RwPiaATT2tFZG9bA/yPeXOR72pWFm+QHrFPdBNybuKUze+5sdd"
    "vs27hT1Hfg0+wLimPMCVAL5o54w9ZUIIvKOkir5G5iW+QCFgPQBoHj4haAe+a3vdPUiLHr7rFqY+31NJPi1g+T290l"
    "8+C0VoPk2DcL0A3g676Q/nPfdchb0g56Q+Mxblu2VDVr6dnae9e3Yfvlv0ij5w1+W9ZuDNvnUyuTxkJm2+XnGavi32"
    "kz4kzhy+jHTxPb72DT6MAAq+XVdaPagedb1i8Yc+ZLB4PtnVWj33Hro+HkB+vtuzYL6KvhE+PvWAvn4/sb1oj6I+9c"
    "igvjQdS74jYAk+X0FNvkOGvr0aJFM+8DOCPmCNZz0fmJG9AmpqvTqwDz69DVu+RwGdPgqWAT64LjE9kqwsvaGlBT6U"
    "Peu9Fxw+vZJpDb55Q4G9e4/vOuBamD7K9Bi+ZUPKPSqRi74ruqY93V81PqqjRT7mtCA+dfb4PcjqVL3QW2Y95HIKvg"
    "5LVT7UNwc+FYlwvj/0iz4+49+9svkYvH2hBb1wcHi8g/vxPL2kFb63r929GugFvZ4vKT0o7Ec+JZY2vfoh7734cao9"
    "A38OPlyHRr+0242+4CYLvRmkZT6j+nw+lqVFvXtxU77pGAG+IlqRPmeshb6pCC29ZaCCPjMCqj1rIRa+Lh0VvpeJob"
    "3Hhjq9DZ8GPi+JAL1O90A+GDDpvCk3XL2X+5m8WxmhPrzhoD4NFP08K8KTPcuV8bx8CYQ+4obTvf4WrLyWISu+SPor"
    "vosORD7dPuK8QUAvPrEuqD74+ZA+6V7HPpdR9b2uy6k9ORdRPY165Tz0l4a9qGUwvMRAQb3631O+U26Ku2RGKr5gW4"
    "49lj9Yvj1/DL4xbzS+YIQAPnMNc77mTes9IDiUPbGz7T3+8HI67HKdPRiyCD5lA0u8TNPJPMHHYb6edwK+ugqGPXFb"
    "3byhfxC+L1GXviDQ9r2xTwg9FTIXPujyQL4ArIQ9dGosvqIyfr4qQ0m+8308vU0rJT1KtBa+3b1aPgaWMz5ncXA9vP"
    "VTPteO870uFfS9S8+3vdrffz1kYwW+fE86viLMLbyO3Vc+sEymPk676L1anBo+mrrdu2P/fT4r5Ow8MR1rPpLMMz71"
    "A4w+eAM4PlZ7FL1xTkM+N9Cmuh/LyT6CXQ0/1ggXPhRZQT76XRW+bd01umeqhz2LKtE9166GPYzQYj66DFi9/yyEva"
    "2ujT1tBAw9qD/2va7ZaDyk6ka+shwjvUits71HgXo+U5x+vSZsML4rynS+h2fBPHA3Ub64e8g924Isvt8BNL4uwv29"
    "N1YJvMM1ZD5wa1Q+BRElvVCwj761YTq9ldFzvZOSE76S8Jo94QGwPA3qUD1mQ+28kS4uvrQ8kL1UxB+87Is0viZ5lr"
    "wKOu29fpORvuqpAD7NNti9/AOgvp5puT2iLU6+AE7zOfUNwj5XLRY+cLkxPYdHUT6PPr4+0yCzPegLrb03TMs96Dl1"
    "PjwEDj7ghXs+4ZR+vN5U0j0aMj4+cdxJPqgU/T0YmJi+ZJojPnNuRj5ce949GaR8PfwJQj4/Mn0+IJQdvm51Ob4fKg"
    "y+qx2VPfzw5r0rD0G+hcuXveKlbD4/zl4+FL4AP9nvoT25aBa8HA7PPV5Upzx+xZM+vHBTPXYjGz3uBea9kpCDPqH2"
    "2bxsDzi8mjBkPqJsTD4QDQi808awvBbQvj4U0mE+930+vvEicL6M2QO+oKxavleZC76BnXm+7gGevftp+j1/gHO+2Q"
    "NTPNZMr73Bguo9iMgzPhwOh727f8m94osrvj/aAL5BNZw9Lg/ePX67WD4wAnW9p4MpPiS1F75tl0Y+fNGUPqv9UL6Y"
    "0Ki9Z3JDPvzrW7wrSfO9Et3HPTbMFj5CFS0+BDp3PnMgTT21m3Y+2uXiPQgSWj1NAzw+CchzPkgX5Tz6+5g85iAcPs"
    "nser3K3YU+jcXlvdBWtz05qkK+FYxSProioT4EYZU+vDckvmaZ0D1wc2i+kOdevjTEhL5Ook2+20TOO3474b3AA3Y6"
    "pRcGPFePFz75YNe9DiHtvSFy2T0yMXu9csZtPtRIxb0ALvG7TfBavcGgET4rSBs930w9vk18DD6b6UU8y4KYvf3xGL"
    "3YBLI9E+WaPkBa/j11eaU9V0gaPhqTAr7zVNi9X6n+vZ+RE76VKzk+IEyePc3NaLyGxtK8MhGBPciOXj6I1hc+3bsQ"
    "vqAQEj4/1Fs+67waPltxjr2e0Cc+rFU1PuaHVz6GW3W+pErCvcA8LL4gW/i94AxJPVYhHD4+l0G+ZIEmPlzWVT5QXv"
    "y9QLoyPbZsA77AU1s9+F/tvbxzx73iXiu+AoM5vvYjiT4FQrk8vdWEPWd+Ab6QdXI+KrMPvlbuM74bNRS+sjIpvkZv"
    "qz4l8RK+ZsaSvZX82TyfJU0+z+scPYk3Nr4E754+Nm9Jvtw5wD27Yzu8jIDEPDp0KD5/XQs+HG+tPRTwubxw/58+5D"
    "toPvnMiDwRJRc928QMPm4/Pj7gDAg+z0YdvTfdIr6liom9Qg0dPngDCrzRMdG83r7KPBvM7b0Z8AO9872cvC2b/z08"
    "0yw+DeBlPm3gaj4mA3G+1s1YvqegFz6wJSK+7egOPpPDEb4FsmY+wEFQPpWdlb7h1Ic+f+liPr7B6rset60+mCF6vp"
    "SUY72dt/08VnhJvUDhNz3+ZcW9HqZyvmBn7LxWvDo++PUsPswmAD5orBQ9IHB+PSvrWr40gaQ983WKvshw0724Sai9"
    "46IkPkDN7ruzlHW+katwvAGwUb6aPdO7eBIjvWmysb2Z+s89+nUcPpqDQ76XrVK+qCRBPiz53bz2J8i9pCOUPTFr8T"
    "2QHCu96ETVvejBrL2jj049OdFkvebD3z1+tHy+5V3DvbIoQz7YQAW8jUX+O3cxIz3x49G9jU+yvUwnAT3Nd8+9kIHT"
    "vdhJBz3AkZ880Oq4vLAhLb68c4y9I6Y6vrK8Bj4ioCm+Oh5MPkpsbz2BNXe+lXwUPuwqfb6AJW68yqlIvgA7XL6HYA"
    "I9V+YlvuY7FD5/Pl++rbgxPmN34j2j4nI+GO6VvXSDQr7d6lG+bHktPq05Kb4Phzu9c2OgvQlamjx8EVK+vHEAvVbx"
    "Jr0Y3Zo+20DBvN+An7162uU9xWnlPSy3Gb56QT6+ZZygPmi13D7VKX4+CF9RPuPjQD69AyM+3dlxvoXdrb5kw2y+kE"
    "fTveCxzj1R6Gm+RPJkvYA6Z7uhgwq+KBDOvTWWPz66hr498CciPqD8ybwWtSe+Cd/SPQhOqr17Dpm9HtOTPoMviD1P"
    "Nc290P9aPjRb4z09PAA+hn2Vvg+dyj0HHlQ+pcygPQ3srb1tnC8+fW5cPss1PD5Pt8A8gM+0O8/5/z242l+9Z80svs"
    "zNqz3K10o9NQToPUB547yo4we9daIWvQM/Rj3yMFW+cptuvkH7nT3luSG+kEisvILP7LzTHAY900RcPoKPyj2Kyg88"
    "oBznvAEDZz2ZE2g8ECY+Pt4ki77I8sy9ZhVzvgePB74xNS8+EdVKvnJhZb7rVC0+cC0Xvjf2Tj40WO89vQYgPcRkij"
    "64J4C+Pe3BPSySHz0tF1e++LW4PICdAT2+jTu+ZTO0O+mEB75dbjI+dENOPvERAb1XJ3W+xqC1vB3VnzspHh0+ZbP/"
    "O+RLgj1SDLA9h9EZvm6vPb7O4Dq+VMPfvGEElD3TkrG8VyByPmHcHb4TnRa9fu7tPfBpSr62HQs9MBufPkMpXj1g4V"
    "Y+Vp8PPiQGBb5WTzI+4lJPvTnNBT7h9CE+tm04PjkGHr53Llg9ZkGXvgPy2Ls9p5c96ffoPavh5j2Al5K9hQCOPRGC"
    "JD6gfsu+K0VHvkbsFT0dhHY7WmFMv0o2kD6+uee94QhVvosuez7CsO8+DdmCPXJ1mb1m66U+vIxbPc2wVL6ocUI+JY"
    "f2PW9viz5G86c9oxi4vTYCZ72X4589+aYWPjhwSj3/vGa+WtQsvhgExrwv5kO8o5YWvgzRd768eP09W9ifvby7h77W"
    "8FA+4EyzPSZCDL4z1VO+RdZQPr7d8LwqkzS+jSbfPcgGn70Ffg28IZwevlThTb5vM7e9sZ42PlhW8L0d6k8+iqCEPf"
    "Frq716/OA9I1cnvnCalL0u1AM+Ojubvo6BTj4CU0M93VYcvtRLhr4b7Ik+Kx8UPgdOa73oa5M9hxwSvoO/gTy+loO7"
    "fg+XPOme/Dx9onA9gIjjPS4XgT4rnrw9y3rPPma9LL6DcQ2+rF6YvXkOIj4QD8k9qxmxvINrIL6NYju+7xhvPk6Lhb"
    "26Rwa9MjUYvhZA9r0bMlo9cjXRPcBcxL2G07a95bxEPsLQ/72FSzm+b/0avT6f1T5vauc7N/+VvD3mpb03iAE++0sV"
    "vpp1Oz6yPXM9odb8O79cVDwa/CC+AcmnPlWUMD5iun2+KJDgvuKHOr6oH2c9KYz0vY4JND6hFCu+r8KIvvqXaD1ikC"
    "i+G5ocvZgXAb6n3528uTKDvvrKY77oolw9SrmdvccdQb7GkUq9265ivkLZgz0pi04+1pGpPlaMp76Ivo88FceDPlwm"
    "jj45FPe9bp98PqZnJj05Mjk+w5sLvtagsz41mpq94zhivY4K7z0p5J8+5oXGvicl4T2WE+g8S0OTPnS6hz7Mft09AB"
    "XtvZp0271IKw49IVcavng+4z1DJCm9xZqMvnMnSz7W2XC+GZ8xvmAwsT3RXzU9fJWuPliJbr7nq8g9R80FPRfRyj1r"
    "zuu9/INJPcOrGT6QPkM+ZxiFvuIOQL7ZcpU+AkgxvSD4OT5fngU9l22lPcaunL3Lefc9ecs0vrr63L2KNi89qdM4Pj"
    "hUsL1ErsY8IVGgPSEu6D0juWW+t1jDuorm+z6Py9g9ITogPZVd6T2wkws+JHanvoVweb21EAy+Ec0xPevM+L1Oq1q9"
    "gzfoPRFnAr6glQw94B2zPaapKb6FpDc9l9NxvX4rCD14xWQ+f8kCPvcKdD1Hf0i+6VyJPWBK8T3MV/C9lrKKvgNuKz"
    "4gr7G9ysFGPahsyL1ZYh4++axTPtHi+j2m/9K9JqcPPgQitT0jutO73gtIvl89BL5kp4e+wn2UPsO2ez6lyoU+0n9B"
    "PZCz4j0JHJM+stL7vQK347xGkIi+i48hPY4/uD1QMMW3mwSdvmtOk73JVmu+21hBvjDw7D30lva+C5QWPrtUTr6+wU"
    "a+I2I0vchLdL6W3Ik+Il8fPsD5ZbzXRxk9DfN7PR+jOb6sjuk8W8lXvsYlOj5qiWC+AKU9vcAUfjyEn6i9NES7vdRA"
    "Xb7Ar2E8UIrovHIuXz6sj6i9wt1FPqDnQTxQCOa9uIZzvdBo6LxgwIw8gaEhPfVG3L3IXGk+uPQgPaOvez3okjs+oL"
    "lcPaHkGz4FLKg9ofioPu1Tgb6CDt27scCJvmtaqzro5pG9iQMoPhjLhT5YfdO+KJw6PlSGMD7etAg+J7LYPab/RD7Z"
    "Gvg9oT/lvYE4Sjw5sjQ+3zaSvFDhib7KdlU9cY+uPQZgT74wKH890qEcPlDe6jxQ77q8ohpEPpKpX74Msum9VGvnvY"
    "YyXT7Ym3e+sB3LPAL8d74gsQa8cNe+PZB3b71FdXM+7V6pu7vIpr45hts96iIFPjYkPz61C7k+ygYivsU7iz6rCMQ9"
    "ApPtPevqOT4uK+U6jIPkvoQbb77gl368UFcAvSoWPj5y4zk+iJQtPkyD6r0w+Ei+siBwvmBMuT1UrWa+3o1/vphgAb"
    "5MJFi+4MXJvfYpIb4+VgO+rGJzPvxLmryqtKU+GSrAvmW7lL0KFi29suuBvv1Bb76OQjE+wCjfvYo9lr7l/rc+A5sS"
    "vSD8pr61VQe/xzUWvhCfSr4g4GQ+zuuxPbcJurze35q+LdezvVcOg76ckMC7MPKHvUc9kr08wJ+9nPxkPVBtTj2PmY"
    "o9/1OovTxeXL2hetu8Eow3vjzsPj7sy0y+b5EJPliDD75+Mi0+OpF5PuANa76vp4w+7hIgvnqYnbwQXyo+8sjBPQpM"
    "eD3WiUO79uMjPA94S77qxBI+zeo4Pu+XHT5d9gu+xI2RPqwiij6w+Rw+lKXNO+GrKT49JZ2+kc2WPu6UAD1SDKc+4y"
    "m/PETsq70gcPC9OCAlPtBGC77okzS9pCMBPlBpzjz0ZVe+WI9+vqzr+L3uHGw+ygU2vjQXDT6yPzc+ADnUvUga4r36"
    "LDi+/431vOQnzTlS0K0+totQPrlqnD0Q5ko9pKvbPWA/cz1J3QE9d0zNPUdaP778q5w+lMScPUVQUD7BN0++9pA5vo"
    "DT/jvOZou9LrYAvoh/0D1AWbe89r91Pe/IOj70Y+u9AP77vRjFTb0bmE+9ba8cvqDYdb1AIOy7+FKsPXrXbD78kT0+"
    "AMDYPPAOgbx0JoM9oDQnvPBiBr3ID7A9GkhQvji2Wb4Au4Q6rC+bvQQ//b1EUm6+8HsrPmAzI7zeigm+532bvVf/RT"
    "6RZge/6NxzPH9f1zzgfoC8sVMxPd5DJ75Xz3E9vx0OPpK2Nz5LqV89SAtbvi7DRb5qSAw+senJvSi+hD4cDHK+h1Yr"
    "vad7xL2a+Be+1wHsvfg5cb6jvyM+PcX3vZfzR77/6409UJQqvb+gMT4z62W+4AmQvW8aMD5In6Q+UO6aPB27bz5rTO"
    "k+rzWyPXiI1j6NlFw+kb0kvkpS3T1Dxzc+wPk1vfwj2z69vIG8jxTUPku7iDzNqaG9NXdnPrlTAj5JS1M+sobaPe86"
    "KT6B4yI+KQk4PTmoO72Q008+DJv+vY1ocDxWtkG+WC6rOrv/q74HMRM+zeZRvowRlD6i3rU9zJhGvg=="
)
