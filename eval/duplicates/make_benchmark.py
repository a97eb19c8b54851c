#!/usr/bin/python3
"""Builds the duplicate benchmark: originals, their transformed copies, other views, overlay traps.

    make_benchmark.py --data ../shared/data --out DIR [--seed 1]

Writes DIR/images/<id>.jpg|png (ids are unique without extension, as `oxbow index build` names images)
and DIR/truth.json. The protocol (what is a positive, a negative, an ignored pair) is in README.md.
Deterministic: the same data, seed and Pillow give the same files. Debian's python3-pil and python3-numpy.
"""

import argparse
import hashlib
import json
import math
import os
import random
import re
import shutil
import sys
import time

import numpy as np
from PIL import Image, ImageDraw, ImageEnhance, ImageFont, ImageOps

FONT_DIR = "/usr/share/fonts/truetype/dejavu"  # Debian fonts-dejavu-core
FONT_BOLD = os.path.join(FONT_DIR, "DejaVuSans-Bold.ttf")
FONT_REGULAR = os.path.join(FONT_DIR, "DejaVuSans.ttf")

CAPTION_TEXT = "RIVERSIDE DAILY  |  Photo of the week  |  (c) Oxbow Press 2024"
CAPTION_TEXT_2 = "Reader submissions - share yours at riverside-daily.example"
FRAME_TITLE = "Photo Viewer - IMG_2041.JPG (68%)"

# Transformations applied to every original: name -> kind of the (original, copy) pair.
TRANSFORMS = [
    ("exact_bytes", "exact"),      # the same file under another name
    ("exact_png", "exact"),        # the same pixels, re-encoded losslessly (PNG; other bytes)
    ("resize_75", "near_copy"),
    ("resize_50", "near_copy"),
    ("jpeg_q90", "near_copy"),
    ("jpeg_q70", "near_copy"),
    ("jpeg_q50", "near_copy"),
    ("jpeg_q30", "near_copy"),
    ("crop_90", "near_copy"),      # crops keep that share of the area, same aspect ratio
    ("crop_70", "near_copy"),
    ("crop_50", "near_copy"),
    ("crop_30", "near_copy"),
    ("rotate_5", "near_copy"),     # canvas expanded: filled corners
    ("rotate_10", "near_copy"),
    ("rotate_20", "near_copy"),
    ("rotate_5_crop", "near_copy"),  # cropped to the largest rectangle without fill
    ("rotate_10_crop", "near_copy"),
    ("rotate_20_crop", "near_copy"),
    ("mirror", "near_copy"),       # horizontal flip
    ("brightness_up", "near_copy"),
    ("brightness_down", "near_copy"),
    ("contrast_up", "near_copy"),
    ("contrast_down", "near_copy"),
    ("caption", "near_copy"),      # overlay "caption": the same text band on every such copy
    ("logo", "near_copy"),         # overlay "logo": the same watermark logo in a corner
    ("frame", "near_copy"),        # overlay "frame": the same screenshot frame (title/menu/side/status bars)
]
OVERLAY_OF = {"caption": "caption", "logo": "logo", "frame": "frame",
              "big_caption": "caption", "big_logo": "logo", "big_frame": "frame"}
CROP_POSITIONS = ["center", "top_left", "top_right", "bottom_left", "bottom_right", "random"]
GRID = 48            # visibility grid over an original, for the overlap of two copies
COPY_PAIR_OVERLAP = 0.5
JPEG_QUALITY = 95    # every generated JPEG except the jpeg_qNN copies
MAX_SIDE = 1024      # originals larger than this are re-encoded at this long side


def sanitize(stem):
    return re.sub(r"[^A-Za-z0-9_-]", "_", stem)


def font(path, size):
    return ImageFont.truetype(path, size)


def text_size(draw, text, fnt):
    x0, y0, x1, y1 = draw.textbbox((0, 0), text, font=fnt)
    return x1 - x0, y1 - y0


def fit_font(draw, text, path, max_w, max_h):
    size = max(6, int(max_h))
    while size > 6:
        w, h = text_size(draw, text, font(path, size))
        if w <= max_w and h <= max_h:
            break
        size -= 1
    return font(path, size)


# ---------------------------------------------------------------- overlays (one design each)

def make_logo(px):
    """The watermark logo: an emblem with rings, a star and lettering (rich in corners and blobs)."""
    s = 512
    im = Image.new("RGBA", (s, s), (0, 0, 0, 0))
    d = ImageDraw.Draw(im)
    d.ellipse((8, 8, s - 8, s - 8), fill=(200, 30, 40, 255), outline=(255, 255, 255, 255), width=14)
    d.ellipse((70, 70, s - 70, s - 70), fill=(255, 255, 255, 255))
    d.ellipse((92, 92, s - 92, s - 92), fill=(20, 40, 120, 255))
    cx, cy, r1, r2 = s / 2, s / 2 - 40, 120, 48
    pts = []
    for i in range(10):
        a = -math.pi / 2 + i * math.pi / 5
        r = r1 if i % 2 == 0 else r2
        pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    d.polygon(pts, fill=(255, 210, 0, 255), outline=(0, 0, 0, 255))
    f = font(FONT_BOLD, 64)
    w, _ = text_size(d, "OXBOW", f)
    d.text((s / 2 - w / 2, s / 2 + 70), "OXBOW", font=f, fill=(255, 255, 255, 255))
    f2 = font(FONT_BOLD, 26)
    w2, _ = text_size(d, "PRESS AGENCY", f2)
    d.text((s / 2 - w2 / 2, s / 2 + 145), "PRESS AGENCY", font=f2, fill=(255, 210, 0, 255))
    for i in range(12):  # tick marks on the outer ring
        a = i * math.pi / 6
        d.line((s / 2 + 215 * math.cos(a), s / 2 + 215 * math.sin(a),
                s / 2 + 245 * math.cos(a), s / 2 + 245 * math.sin(a)), fill=(255, 255, 255, 255), width=8)
    return im.resize((px, px), Image.LANCZOS)


def add_logo(img, rng, big):
    img = img.convert("RGB")
    w, h = img.size
    if big:
        px = int(0.6 * min(w, h))
        x, y = (w - px) // 2, (h - px) // 2
        alpha = 1.0
    else:
        px = max(48, int(0.24 * min(w, h)))
        m = max(6, int(0.03 * min(w, h)))
        corner = rng.choice(["top_left", "top_right", "bottom_left", "bottom_right"])
        x = m if "left" in corner else w - px - m
        y = m if "top" in corner else h - px - m
        alpha = 0.85
    logo = make_logo(px)
    if alpha < 1.0:
        a = logo.getchannel("A").point(lambda v: int(v * alpha))
        logo.putalpha(a)
    out = img.copy()
    out.paste(logo, (x, y), logo)
    return out


def add_caption(img, rng, big):
    img = img.convert("RGB")
    w, h = img.size
    band_h = int(h * (0.30 if big else 0.13))
    top = rng.random() < 0.3 and not big
    y0 = 0 if top else h - band_h
    overlay = Image.new("RGBA", (w, h), (0, 0, 0, 0))
    d = ImageDraw.Draw(overlay)
    d.rectangle((0, y0, w, y0 + band_h), fill=(0, 0, 0, 255 if big else 165))
    lines = [CAPTION_TEXT, CAPTION_TEXT_2] if big else [CAPTION_TEXT]
    line_h = band_h * 0.8 / len(lines)
    y = y0 + band_h * 0.1
    for i, line in enumerate(lines):
        f = fit_font(d, line, FONT_BOLD if i == 0 else FONT_REGULAR, w * 0.94, line_h * 0.8)
        tw, th = text_size(d, line, f)
        d.text(((w - tw) / 2, y + (line_h - th) / 2), line, font=f, fill=(255, 255, 255, 255))
        y += line_h
    out = img.convert("RGBA")
    out.alpha_composite(overlay)
    return out.convert("RGB")


FRAME_SIDEBAR = ["Library", "  All photos", "  Favourites", "  Recently added", "Albums",
                 "  Holidays 2023", "  Family", "  Architecture", "  Screenshots", "Devices",
                 "  Camera", "  Phone", "Tags", "  #travel", "  #city", "  #weekend"]


def draw_frame_chrome(d, cw, ch, title_h, menu_h, side_w, status_h):
    """The same window chrome on every frame: fixed pixel sizes anchored at the corners."""
    d.rectangle((0, 0, cw, title_h), fill=(45, 45, 52))
    for i, c in enumerate([(236, 95, 87), (245, 190, 60), (98, 197, 84)]):
        d.ellipse((12 + i * 24, 9, 28 + i * 24, 25), fill=c)
    d.text((96, 7), FRAME_TITLE, font=font(FONT_BOLD, 16), fill=(235, 235, 235))
    d.rectangle((0, title_h, cw, title_h + menu_h), fill=(228, 228, 232))
    x = 12
    for item in ["File", "Edit", "View", "Image", "Tools", "Window", "Help"]:
        d.text((x, title_h + 6), item, font=font(FONT_REGULAR, 15), fill=(20, 20, 20))
        x += 16 + 9 * len(item)
    for i in range(8):  # toolbar icons
        ix = cw - 30 - i * 30
        shape = i % 3
        box = (ix, title_h + 5, ix + 20, title_h + menu_h - 5)
        if shape == 0:
            d.rectangle(box, outline=(60, 60, 60), width=2)
        elif shape == 1:
            d.ellipse(box, outline=(60, 60, 60), width=2)
        else:
            d.polygon([(box[0], box[3]), ((box[0] + box[2]) / 2, box[1]), (box[2], box[3])], outline=(60, 60, 60))
    top = title_h + menu_h
    d.rectangle((0, top, side_w, ch - status_h), fill=(243, 243, 246))
    d.line((side_w, top, side_w, ch - status_h), fill=(190, 190, 196), width=2)
    y = top + 10
    for item in FRAME_SIDEBAR:
        if y > ch - status_h - 22:
            break
        bold = not item.startswith(" ")
        d.text((12, y), item.strip() if bold else "   " + item.strip(),
               font=font(FONT_BOLD if bold else FONT_REGULAR, 14), fill=(30, 30, 30))
        y += 22
    d.rectangle((0, ch - status_h, cw, ch), fill=(50, 110, 200))
    d.text((10, ch - status_h + 4), "IMG_2041.JPG   4032 x 3024   2.4 MB   f/1.8  1/120 s  ISO 50",
           font=font(FONT_REGULAR, 14), fill=(255, 255, 255))


def add_frame(img, rng, big):
    """A screenshot of a photo viewer showing the image. Returns (image, affine original->frame, content box)."""
    img = img.convert("RGB")
    w, h = img.size
    title_h, menu_h, status_h = 32, 30, 24
    side_w = 300 if big else 170
    pad = 16
    if big:
        cw, ch = 1024, 768
        # The photo fills only about a third of the screenshot: the rest is the same chrome plus a filmstrip.
        box_w, box_h = 520, 380
        s = min(box_w / w, box_h / h)
    else:
        s = min(1.0, 900.0 / max(w, h))
        box_w, box_h = int(round(w * s)), int(round(h * s))
        cw = side_w + 2 * pad + box_w
        ch = title_h + menu_h + status_h + 2 * pad + box_h
    pw, ph = int(round(w * s)), int(round(h * s))
    canvas = Image.new("RGB", (cw, ch), (30, 30, 34))
    d = ImageDraw.Draw(canvas)
    draw_frame_chrome(d, cw, ch, title_h, menu_h, side_w, status_h)
    area_x0, area_y0 = side_w + pad, title_h + menu_h + pad
    area_w = cw - side_w - 2 * pad
    x0 = area_x0 + (area_w - pw) // 2
    y0 = area_y0 + ((box_h - ph) // 2 if big else 0)
    if big:  # filmstrip of thumbnails under the photo, always the same
        fy = area_y0 + box_h + 20
        for i in range(6):
            fx = area_x0 + i * 112
            d.rectangle((fx, fy, fx + 100, fy + 70), fill=(70 + 25 * i, 90, 140 - 10 * i), outline=(220, 220, 220), width=2)
            d.text((fx + 8, fy + 74), "IMG_20%02d" % (35 + i), font=font(FONT_REGULAR, 12), fill=(220, 220, 220))
    canvas.paste(img.resize((pw, ph), Image.LANCZOS), (x0, y0))
    sx, sy = pw / w, ph / h
    affine = [sx, 0.0, x0 + 0.5 * sx - 0.5, 0.0, sy, y0 + 0.5 * sy - 0.5]
    return canvas, affine, (x0, y0, x0 + pw, y0 + ph)


# ---------------------------------------------------------------- geometric transformations

def rotated_rect_max_area(w, h, angle):
    """Largest axis-aligned rectangle inside a w x h rectangle rotated by `angle` radians."""
    long_side, short_side = (w, h) if w >= h else (h, w)
    sin_a, cos_a = abs(math.sin(angle)), abs(math.cos(angle))
    if short_side <= 2.0 * sin_a * cos_a * long_side or abs(sin_a - cos_a) < 1e-10:
        x = 0.5 * short_side
        wr, hr = (x / sin_a, x / cos_a) if w >= h else (x / cos_a, x / sin_a)
    else:
        cos_2a = cos_a * cos_a - sin_a * sin_a
        wr, hr = (w * cos_a - h * sin_a) / cos_2a, (h * cos_a - w * sin_a) / cos_2a
    return wr, hr


def compose(a, b):
    """Affine b after a (both [a11,a12,tx,a21,a22,ty])."""
    A = np.array([[a[0], a[1], a[2]], [a[3], a[4], a[5]], [0, 0, 1]])
    B = np.array([[b[0], b[1], b[2]], [b[3], b[4], b[5]], [0, 0, 1]])
    C = B @ A
    return [float(v) for v in (C[0, 0], C[0, 1], C[0, 2], C[1, 0], C[1, 1], C[1, 2])]


def apply_transform(name, img, rng):
    """Returns (image or None for exact_bytes, save format, jpeg quality, affine original->copy,
    content box in the copy (x0, y0, x1, y1) or None for the whole copy, details)."""
    w, h = img.size
    ident = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    if name == "exact_bytes":
        return None, None, None, ident, None, {}
    if name == "exact_png":
        return img, "PNG", None, ident, None, {}
    if name.startswith("resize_"):
        f = int(name.split("_")[1]) / 100.0
        nw, nh = max(1, int(round(w * f))), max(1, int(round(h * f)))
        sx, sy = nw / w, nh / h
        return (img.resize((nw, nh), Image.LANCZOS), "JPEG", JPEG_QUALITY,
                [sx, 0, 0.5 * sx - 0.5, 0, sy, 0.5 * sy - 0.5], None, {"scale": f})
    if name.startswith("jpeg_q"):
        return img, "JPEG", int(name[6:]), ident, None, {}
    if name.startswith("crop_"):
        a = int(name.split("_")[1]) / 100.0
        cw, ch = max(1, int(round(w * math.sqrt(a)))), max(1, int(round(h * math.sqrt(a))))
        pos = rng.choice(CROP_POSITIONS)
        if pos == "center":
            x0, y0 = (w - cw) // 2, (h - ch) // 2
        elif pos == "random":
            x0, y0 = rng.randint(0, w - cw), rng.randint(0, h - ch)
        else:
            x0 = 0 if "left" in pos else w - cw
            y0 = 0 if "top" in pos else h - ch
        return (img.crop((x0, y0, x0 + cw, y0 + ch)), "JPEG", JPEG_QUALITY,
                [1, 0, -x0, 0, 1, -y0], None, {"area": a, "position": pos, "box": [x0, y0, x0 + cw, y0 + ch]})
    if name.startswith("rotate_"):
        parts = name.split("_")
        deg = int(parts[1]) * rng.choice([1, -1])
        crop = len(parts) > 2
        fill = rng.choice([(0, 0, 0), (255, 255, 255)])
        rot = img.rotate(deg, resample=Image.BICUBIC, expand=True, fillcolor=fill)
        W, H = rot.size
        t = math.radians(deg)
        c, s = math.cos(t), math.sin(t)
        # PIL rotates counter-clockwise on screen (y down): x' = c*dx + s*dy, y' = -s*dx + c*dy about the centres
        cx, cy = w / 2.0, h / 2.0
        CX, CY = W / 2.0, H / 2.0
        aff = [c, s, CX - c * cx - s * cy, -s, c, CY + s * cx - c * cy]
        details = {"degrees": deg, "fill": list(fill)}
        if crop:
            wr, hr = rotated_rect_max_area(w, h, t)
            wr, hr = int(math.floor(wr)) - 2, int(math.floor(hr)) - 2
            x0, y0 = int(round(CX - wr / 2.0)), int(round(CY - hr / 2.0))
            rot = rot.crop((x0, y0, x0 + wr, y0 + hr))
            aff = compose(aff, [1, 0, -x0, 0, 1, -y0])
            details["kept_area"] = round(wr * hr / float(w * h), 3)
            return rot, "JPEG", JPEG_QUALITY, aff, None, details
        # content = the rotated original: the filled corners are not content
        return rot, "JPEG", JPEG_QUALITY, aff, None, details
    if name == "mirror":
        return ImageOps.mirror(img), "JPEG", JPEG_QUALITY, [-1, 0, w - 1, 0, 1, 0], None, {}
    if name == "brightness_up":
        return ImageEnhance.Brightness(img).enhance(1.4), "JPEG", JPEG_QUALITY, ident, None, {"factor": 1.4}
    if name == "brightness_down":
        return ImageEnhance.Brightness(img).enhance(0.6), "JPEG", JPEG_QUALITY, ident, None, {"factor": 0.6}
    if name == "contrast_up":
        return ImageEnhance.Contrast(img).enhance(1.5), "JPEG", JPEG_QUALITY, ident, None, {"factor": 1.5}
    if name == "contrast_down":
        return ImageEnhance.Contrast(img).enhance(0.5), "JPEG", JPEG_QUALITY, ident, None, {"factor": 0.5}
    if name in ("caption", "big_caption"):
        return add_caption(img, rng, name.startswith("big")), "JPEG", JPEG_QUALITY, ident, None, {}
    if name in ("logo", "big_logo"):
        return add_logo(img, rng, name.startswith("big")), "JPEG", JPEG_QUALITY, ident, None, {}
    if name in ("frame", "big_frame"):
        out, aff, box = add_frame(img, rng, name.startswith("big"))
        return out, "JPEG", JPEG_QUALITY, aff, box, {}
    raise ValueError(name)


def visibility(affine, w, h, copy_size, box):
    """Which cells of a GRID x GRID grid over the w x h original are visible in the copy."""
    xs = (np.arange(GRID) + 0.5) * w / GRID
    ys = (np.arange(GRID) + 0.5) * h / GRID
    X, Y = np.meshgrid(xs, ys)
    a = affine
    U = a[0] * X + a[1] * Y + a[2]
    V = a[3] * X + a[4] * Y + a[5]
    x0, y0, x1, y1 = box if box else (0, 0, copy_size[0], copy_size[1])
    return (U >= x0) & (U < x1) & (V >= y0) & (V < y1)


# ---------------------------------------------------------------- sources

def list_images(folder):
    exts = (".jpg", ".jpeg", ".png")
    return sorted(f for f in os.listdir(folder) if f.lower().endswith(exts))


def exif_orientation(path):
    try:
        return Image.open(path).getexif().get(0x0112) or 1
    except Exception:
        return 1


def usable_as_original(path, min_side=300):
    im = Image.open(path)
    return min(im.size) >= min_side and exif_orientation(path) in (0, 1) and im.mode in ("RGB", "L", "RGBA")


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class Writer:
    def __init__(self, out_dir):
        self.dir = os.path.join(out_dir, "images")
        self.images = []
        self.ids = set()

    def add(self, image_id, record, src_path=None, img=None, fmt=None, quality=None):
        assert image_id not in self.ids, image_id
        self.ids.add(image_id)
        if src_path is not None:
            ext = os.path.splitext(src_path)[1].lower()
            ext = ".jpg" if ext == ".jpeg" else ext
            dst = os.path.join(self.dir, image_id + ext)
            shutil.copyfile(src_path, dst)
            size = Image.open(dst).size
        else:
            ext = ".png" if fmt == "PNG" else ".jpg"
            dst = os.path.join(self.dir, image_id + ext)
            if fmt == "PNG":
                img.save(dst, format="PNG", compress_level=6)
            else:
                img.convert("RGB").save(dst, format="JPEG", quality=quality)
            size = img.size
        rec = {"id": image_id, "file": os.path.basename(dst), "size": list(size)}
        rec.update(record)
        rec["sha256"] = sha256(dst)
        self.images.append(rec)
        return rec


def load_original(path):
    """Decoded pixels of an original (RGB or L), at most MAX_SIDE on the long side."""
    im = Image.open(path)
    im.load()
    if im.mode not in ("RGB", "L"):
        im = im.convert("RGB")
    if max(im.size) > MAX_SIDE:
        f = MAX_SIDE / float(max(im.size))
        im = im.resize((int(round(im.width * f)), int(round(im.height * f))), Image.LANCZOS)
        return im, True
    return im, False


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data"),
                    help="the shared data folder (paris6k/, groups_dev/, distractors/)")
    ap.add_argument("--out", required=True, help="output folder (outside the repository) without images/ or truth.json")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--paris-per-landmark", type=int, default=2, help="originals from each Paris landmark")
    ap.add_argument("--groups-originals", type=int, default=8, help="groups_dev groups that give one original each")
    ap.add_argument("--distractor-originals", type=int, default=12)
    ap.add_argument("--overlay-only", type=int, default=8, help="unrelated photos per big overlay (logo, caption, frame)")
    ap.add_argument("--plain-distractors", type=int, default=60, help="unrelated distractor photos, untransformed")
    args = ap.parse_args()

    t_start = time.time()
    data = os.path.abspath(args.data)
    out = os.path.abspath(args.out)
    images_dir = os.path.join(out, "images")
    if (os.path.isdir(images_dir) and os.listdir(images_dir)) or os.path.exists(os.path.join(out, "truth.json")):
        sys.exit("make_benchmark: %s already holds a benchmark (images/ or truth.json)" % out)
    if os.path.realpath(out).startswith(os.path.realpath(os.path.join(os.path.dirname(__file__), "..", "..")) + os.sep):
        sys.exit("make_benchmark: write the benchmark outside the repository")
    for p in (FONT_BOLD, FONT_REGULAR):
        if not os.path.exists(p):
            sys.exit("make_benchmark: %s missing (Debian fonts-dejavu-core; scripts/install-deps.sh)" % p)
    os.makedirs(images_dir, exist_ok=True)
    rng = random.Random(args.seed)
    wr = Writer(out)

    paris_dir = os.path.join(data, "paris6k", "images")
    groups_dir = os.path.join(data, "groups_dev")
    distractor_dir = os.path.join(data, "distractors")

    # --- choose the originals
    originals = []  # (id, path, origin, scene, group)
    paris = list_images(paris_dir)
    landmarks = sorted({f.split("_")[1] for f in paris})
    for lm in landmarks:
        cands = [f for f in paris if f.split("_")[1] == lm and usable_as_original(os.path.join(paris_dir, f))]
        for f in sorted(rng.sample(cands, args.paris_per_landmark)):
            originals.append(("p-" + sanitize(os.path.splitext(f)[0]), os.path.join(paris_dir, f), "paris",
                              "paris:" + lm, None))
    groups = sorted(g for g in os.listdir(groups_dir) if os.path.isdir(os.path.join(groups_dir, g)))
    group_files = {g: list_images(os.path.join(groups_dir, g)) for g in groups}
    eligible = [g for g in groups if any(usable_as_original(os.path.join(groups_dir, g, f)) for f in group_files[g])]
    chosen_groups = sorted(rng.sample(eligible, args.groups_originals))
    group_original = {}
    for g in chosen_groups:
        cands = [f for f in group_files[g] if usable_as_original(os.path.join(groups_dir, g, f))]
        f = rng.choice(cands)
        group_original[g] = f
    distractors = [f for f in list_images(distractor_dir)]
    rng.shuffle(distractors)
    d_orig, rest = [], []
    for f in distractors:
        if len(d_orig) < args.distractor_originals and usable_as_original(os.path.join(distractor_dir, f)):
            d_orig.append(f)
        else:
            rest.append(f)
    d_overlay = rest[:3 * args.overlay_only]
    d_plain = rest[3 * args.overlay_only:3 * args.overlay_only + args.plain_distractors]

    # --- groups_dev: every photo, untransformed (the other views); one per chosen group is also an original
    for g in groups:
        for f in group_files[g]:
            image_id = "g-%s-%s" % (g, sanitize(os.path.splitext(f)[0]))
            path = os.path.join(groups_dir, g, f)
            if group_original.get(g) == f:
                originals.append((image_id, path, "groups_dev", "groups_dev:" + g, g))
            else:
                wr.add(image_id, {"origin": "groups_dev", "source": image_id, "scene": "groups_dev:" + g,
                                  "group": g, "transform": "original", "overlay": None, "mirrored": False,
                                  "affine_from_source": [1, 0, 0, 0, 1, 0], "from": os.path.relpath(path, data)},
                       src_path=path)
    for f in sorted(d_orig):
        originals.append(("d-" + sanitize(os.path.splitext(f)[0]), os.path.join(distractor_dir, f), "distractors",
                          None, None))

    # --- originals and their copies
    vis = {}  # image id -> visibility grid over its source
    for oid, path, origin, scene, group in sorted(originals):
        img, reencoded = load_original(path)
        base = {"origin": origin, "source": oid, "scene": scene, "group": group, "overlay": None,
                "from": os.path.relpath(path, data)}
        orec = dict(base, transform="original", mirrored=False, affine_from_source=[1, 0, 0, 0, 1, 0])
        if reencoded or Image.open(path).mode not in ("RGB", "L"):
            orec["note"] = "re-encoded from the source (long side > %d or not RGB/L)" % MAX_SIDE
            wr.add(oid, orec, img=img, fmt="JPEG", quality=JPEG_QUALITY)
            orig_path = os.path.join(wr.dir, oid + ".jpg")
        else:
            rec = wr.add(oid, orec, src_path=path)
            orig_path = os.path.join(wr.dir, rec["file"])
        w, h = img.size
        vis[oid] = np.ones((GRID, GRID), bool)
        for name, _ in TRANSFORMS:
            cid = "%s--%s" % (oid, name)
            out_img, fmt, q, aff, box, details = apply_transform(name, img, rng)
            rec = dict(base, transform=name, overlay=OVERLAY_OF.get(name), mirrored=(name == "mirror"),
                       affine_from_source=[round(v, 6) for v in aff])
            if details:
                rec["details"] = details
            if out_img is None:
                rec = wr.add(cid, rec, src_path=orig_path)
                size = rec["size"]
            else:
                rec = wr.add(cid, rec, img=out_img, fmt=fmt, quality=q)
                size = out_img.size
            if box:
                rec["content_box"] = list(box)
            vis[cid] = visibility(aff, w, h, size, box)
            if name == "exact_png" and rec["sha256"] == sha256(orig_path):
                sys.exit("make_benchmark: the lossless re-encoding of %s kept its bytes" % oid)

    # --- overlay-only negatives: unrelated photos carrying the same big overlay
    for i, kind in enumerate(["big_logo", "big_caption", "big_frame"]):
        for f in sorted(d_overlay[i * args.overlay_only:(i + 1) * args.overlay_only]):
            img, _ = load_original(os.path.join(distractor_dir, f))
            sid = "d-" + sanitize(os.path.splitext(f)[0])
            out_img, fmt, q, aff, box, _ = apply_transform(kind, img, rng)
            rec = {"origin": "distractors", "source": sid, "scene": None, "group": None, "transform": kind,
                   "overlay": OVERLAY_OF[kind], "mirrored": False, "affine_from_source": [round(v, 6) for v in aff],
                   "from": os.path.relpath(os.path.join(distractor_dir, f), data)}
            wr.add("%s--%s" % (sid, kind), rec, img=out_img, fmt=fmt, quality=q)

    # --- plain unrelated photos
    for f in sorted(d_plain):
        sid = "d-" + sanitize(os.path.splitext(f)[0])
        wr.add(sid, {"origin": "distractors", "source": sid, "scene": None, "group": None, "transform": "original",
                     "overlay": None, "mirrored": False, "affine_from_source": [1, 0, 0, 0, 1, 0],
                     "from": os.path.relpath(os.path.join(distractor_dir, f), data)},
               src_path=os.path.join(distractor_dir, f))

    # --- pairs
    images = sorted(wr.images, key=lambda r: r["id"])
    kind_of = dict(TRANSFORMS)
    positives, ignore, overlay_neg = [], [], []
    exactish = {"original", "exact_bytes", "exact_png"}
    by_source = {}
    for r in images:
        by_source.setdefault(r["source"], []).append(r)
    # same source: originals vs copies, and copies vs copies
    for src, recs in sorted(by_source.items()):
        recs = sorted(recs, key=lambda r: r["id"])
        for i in range(len(recs)):
            for j in range(i + 1, len(recs)):
                a, b = recs[i], recs[j]
                if a["transform"] != "original" and b["transform"] == "original":
                    a, b = b, a
                mirrored = a["mirrored"] != b["mirrored"]
                if a["transform"] == "original":
                    t = b["transform"]
                    positives.append({"a": a["id"], "b": b["id"], "kind": kind_of[t], "transformation": t,
                                      "mirrored": mirrored, "accept_kinds": [kind_of[t]]})
                    continue
                va, vb = vis[a["id"]], vis[b["id"]]
                overlap = float((va & vb).sum()) / max(1, min(va.sum(), vb.sum()))
                if a["transform"] in exactish and b["transform"] in exactish:
                    kind = "exact"
                else:
                    kind = "near_copy"
                if overlap >= COPY_PAIR_OVERLAP:
                    positives.append({"a": a["id"], "b": b["id"], "kind": kind, "transformation": "copy_pair",
                                      "mirrored": mirrored, "accept_kinds": [kind],
                                      "overlap": round(overlap, 3)})
                else:
                    ignore.append({"a": a["id"], "b": b["id"], "reason": "copies of one photo overlapping by %.2f"
                                   % overlap})
    # different sources
    by_scene = {}
    for r in images:
        if r["scene"]:
            by_scene.setdefault(r["scene"], []).append(r)
    for scene, recs in sorted(by_scene.items()):
        recs = sorted(recs, key=lambda r: r["id"])
        for i in range(len(recs)):
            for j in range(i + 1, len(recs)):
                a, b = recs[i], recs[j]
                if a["source"] == b["source"]:
                    continue
                if scene.startswith("groups_dev:") and a["transform"] == "original" and b["transform"] == "original":
                    accept = ["same_scene"]
                    if a["group"] == "cs131_cereal_shelf":  # shelf, shelf_dark (synthetic darkening), shelf_soldout
                        accept = ["same_scene", "near_copy"]
                    positives.append({"a": a["id"], "b": b["id"], "kind": "same_scene", "transformation": "same_scene",
                                      "mirrored": False, "accept_kinds": accept})
                elif scene.startswith("groups_dev:"):
                    ignore.append({"a": a["id"], "b": b["id"], "reason": "a transformed copy against another view"})
                else:
                    ignore.append({"a": a["id"], "b": b["id"], "reason": "two photos of one Paris landmark"})
    listed = {tuple(sorted((p["a"], p["b"]))) for p in positives} | {tuple(sorted((p["a"], p["b"]))) for p in ignore}
    by_overlay = {}
    for r in images:
        if r["overlay"]:
            by_overlay.setdefault(r["overlay"], []).append(r)
    for ov, recs in sorted(by_overlay.items()):
        recs = sorted(recs, key=lambda r: r["id"])
        for i in range(len(recs)):
            for j in range(i + 1, len(recs)):
                a, b = recs[i], recs[j]
                key = tuple(sorted((a["id"], b["id"])))
                if a["source"] == b["source"] or key in listed:
                    continue
                overlay_neg.append({"a": a["id"], "b": b["id"], "overlay": ov,
                                    "transformations": [a["transform"], b["transform"]]})

    n = len(images)
    counts = {"images": n, "pairs": n * (n - 1) // 2, "positives": len(positives),
              "ignored": len(ignore), "overlay_negatives": len(overlay_neg),
              "unrelated_negatives": n * (n - 1) // 2 - len(positives) - len(ignore) - len(overlay_neg),
              "originals": len(originals), "copies_per_original": len(TRANSFORMS)}
    per_t = {}
    for p in positives:
        per_t[p["transformation"]] = per_t.get(p["transformation"], 0) + 1
    counts["positives_by_transformation"] = per_t
    truth = {
        "benchmark": "oxbow duplicate benchmark",
        "version": 1,
        "seed": args.seed,
        "settings": {k: getattr(args, k) for k in ("paris_per_landmark", "groups_originals", "distractor_originals",
                                                   "overlay_only", "plain_distractors")},
        "transformations": [{"name": t, "kind": k} for t, k in TRANSFORMS],
        "protocol": "pairs are unordered; positives and ignored pairs are listed; overlay_negatives are listed "
                    "negatives; every other pair of images is an unrelated negative",
        "counts": counts,
        "images": images,
        "positives": positives,
        "overlay_negatives": overlay_neg,
        "ignore": ignore,
    }
    with open(os.path.join(out, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1)
    print(json.dumps(counts, indent=1))
    print("make_benchmark: %d images in %s (%.1f s)" % (n, out, time.time() - t_start))


if __name__ == "__main__":
    main()
