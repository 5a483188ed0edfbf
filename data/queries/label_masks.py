"""How data/queries/masks/*.png were made: GrabCut seeded by the hand-drawn box plus hand-drawn hints
(label_hints.json: rough outlines refined within +-r px, foreground/background polygons, other objects'
masks as background), then checked by eye on the overlay sheets this writes, and the hints fixed.

    OSCAR_SHARED_DATA=../shared/data python data/queries/label_masks.py [QUERY_ID ...]

Writes OUT/<query_id>.npy and a contact sheet (photo with the mask outline beside the cut-out object);
OUT defaults to /tmp/oscar_label_masks. Converting the .npy masks to 1-bit PNGs is one line of PIL
(Image.fromarray(mask).convert("1").save(...)). Hints that exclude another object read its mask from
OUT, so run the script twice on a fresh OUT.
"""

import json
import os
import sys

import cv2
import numpy as np
from PIL import Image, ImageDraw
from scipy import ndimage

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(os.environ["OSCAR_SHARED_DATA"], "photos", "posecnn_demo")
Q = [json.loads(line) for line in open(os.path.join(HERE, "ycb_photos.jsonl"))]
HINTS = json.load(open(os.path.join(HERE, "label_hints.json")))
OUT = os.environ.get("OUT", "/tmp/oscar_label_masks")
os.makedirs(OUT, exist_ok=True)


def poly_mask(shape, polys):
    im = Image.new("L", (shape[1], shape[0]), 0)
    d = ImageDraw.Draw(im)
    if polys and isinstance(polys[0][0], (int, float)):
        polys = [polys]
    for p in polys:
        d.polygon([tuple(v) for v in p], fill=1)
    return np.asarray(im, bool)


def run(q):
    qid = q["query_id"]
    photo = q["image"].split("/")[-1]
    img = np.asarray(Image.open(f"{ROOT}/{photo}").convert("RGB"))
    h = HINTS.get(qid, {})
    box = h.get("box", q["box"])
    x0, y0, x1, y1 = box
    if "poly" in h:  # a hand outline is the mask
        m = poly_mask(img.shape, h["poly"])
        if "minus" in h:
            m &= ~poly_mask(img.shape, h["minus"])
    else:
        gc = np.full(img.shape[:2], cv2.GC_BGD, np.uint8)
        gc[y0:y1, x0:x1] = cv2.GC_PR_FGD
        if h.get("outline"):  # a rough hand outline: refined by GrabCut within +-R px of its edge
            r = h.get("r", 4)
            pm = poly_mask(img.shape, h["outline"])
            dil = ndimage.binary_dilation(pm, iterations=r)
            ero = ndimage.binary_erosion(pm, iterations=r)
            gc[:] = cv2.GC_BGD
            gc[dil] = cv2.GC_PR_BGD
            gc[pm] = cv2.GC_PR_FGD
            gc[ero] = cv2.GC_FGD
        if h.get("pr_bg"):
            gc[poly_mask(img.shape, h["pr_bg"]) & (gc == cv2.GC_PR_FGD)] = cv2.GC_PR_BGD
        if h.get("fg"):
            gc[poly_mask(img.shape, h["fg"])] = cv2.GC_FGD
        if h.get("bg"):
            gc[poly_mask(img.shape, h["bg"])] = cv2.GC_BGD
        for other in h.get("exclude", []):  # another object's mask (made first: run the script twice)
            if os.path.exists(f"{OUT}/{other}.npy"):
                gc[np.load(f"{OUT}/{other}.npy")] = cv2.GC_BGD
        bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
        cv2.grabCut(img[..., ::-1].copy(), gc, None, bgd, fgd, 10, cv2.GC_INIT_WITH_MASK)
        m = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
        m = ndimage.binary_opening(m, iterations=1)
        lab, n = ndimage.label(m)
        if n:
            sizes = ndimage.sum(m, lab, range(1, n + 1))
            m = np.isin(lab, 1 + np.flatnonzero(sizes >= 0.15 * sizes.max()))
        if h.get("fill", True):
            m = ndimage.binary_fill_holes(m)
        if h.get("minus"):
            m &= ~poly_mask(img.shape, h["minus"])
        if h.get("plus"):
            m |= poly_mask(img.shape, h["plus"])
    np.save(f"{OUT}/{qid}.npy", m)
    # overlay: crop around the box with margin, 2x
    ov = img.copy()
    cnt, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(ov, cnt, -1, (255, 0, 255), 1)
    cv2.rectangle(ov, (x0, y0), (x1 - 1, y1 - 1), (0, 200, 255), 1)
    if GRID:
        for gx in range(0, img.shape[1], 20):
            ov[:, gx] = (ov[:, gx] * 0.5 + np.array([0, 255, 255]) * 0.5) if gx % 100 else (0, 255, 255)
        for gy in range(0, img.shape[0], 20):
            ov[gy, :] = (ov[gy, :] * 0.5 + np.array([0, 255, 255]) * 0.5) if gy % 100 else (0, 255, 255)
    cut = np.full_like(img, 205)
    cut[m] = img[m]
    mg = 20
    cx0, cy0, cx1, cy1 = (
        max(0, x0 - mg),
        max(0, y0 - mg),
        min(img.shape[1], x1 + mg),
        min(img.shape[0], y1 + mg),
    )
    crop = Image.fromarray(np.concatenate([ov[cy0:cy1, cx0:cx1], cut[cy0:cy1, cx0:cx1]], axis=1))
    s = min(TW / crop.size[0], TH / crop.size[1])
    crop = crop.resize((round(crop.size[0] * s), round(crop.size[1] * s)), Image.NEAREST)
    return qid, crop, box


GRID = os.environ.get("GRID") == "1"
TW, TH = 740, 520
ids = sys.argv[1:] or [q["query_id"] for q in Q]
tiles = [run(q) for q in Q if q["query_id"] in ids]
W = 2 if len(tiles) > 1 else 1
rows = (len(tiles) + W - 1) // W
sheet = Image.new("RGB", (W * (TW + 10), rows * (TH + 25)), (40, 40, 40))
d = ImageDraw.Draw(sheet)
for i, (qid, crop, box) in enumerate(tiles):
    x, y = (i % W) * (TW + 10), (i // W) * (TH + 25)
    sheet.paste(crop, (x, y + 20))
    d.text((x + 2, y + 2), f"{qid} {box}", fill=(255, 255, 0))
sheet.save(os.environ.get("SHEET", os.path.join(OUT, "sheet.png")))
print("ok", len(tiles))
