"""HMI routes for the black box: list the saved bags, download one as a zip, save now (``recorder/save``).

The recorder service of ``zagv up`` writes its bags to ``<state_dir>/blackbox`` (the run folder both services share);
the routes read that folder.
"""

from __future__ import annotations

import asyncio
import io
import re
import zipfile
from pathlib import Path

import msgspec
from litestar import Request, Response, get, post
from litestar.exceptions import NotFoundException
from litestar.status_codes import HTTP_200_OK

from proto.messages import BlackBoxSaveRequest
from services.common.bagfiles import list_bags

BAG_NAME = re.compile(r"^blackbox_[A-Za-z0-9_.~-]{1,120}$")


class SavedBagOut(msgspec.Struct):
    name: str
    size_bytes: int
    duration_s: float
    messages: int
    modified_s: float


class BlackBoxSaved(msgspec.Struct):
    ok: bool
    message: str = ""


def _folder(request: Request) -> Path:
    return request.app.state.backend.state_dir / "blackbox"


@get("/blackbox", summary="Saved black box bags (rosbag2/MCAP), newest first")
async def blackbox_list(request: Request) -> list[SavedBagOut]:
    bags = await asyncio.to_thread(list_bags, _folder(request))
    return [SavedBagOut(b.name, b.size_bytes, b.duration_s, b.messages, b.modified_s) for b in bags]


def _zip(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for f in sorted(folder.iterdir()):
            if f.is_file():
                z.write(f, f"{folder.name}/{f.name}")
    return buf.getvalue()


@get("/blackbox/{name:str}", media_type="application/zip", summary="One saved black box bag as a zip")
async def blackbox_download(request: Request, name: str) -> Response[bytes]:
    stem = name.removesuffix(".zip")
    bag = _folder(request) / stem
    if not BAG_NAME.match(stem) or not (bag / "metadata.yaml").is_file():
        raise NotFoundException(f"no saved black box bag {name!r}")
    data = await asyncio.to_thread(_zip, bag)
    return Response(data, media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{stem}.zip"'})


@post("/blackbox/save", status_code=HTTP_200_OK, summary="Save the black box now (the last minutes of every topic)")
async def blackbox_save(request: Request) -> BlackBoxSaved:
    backend = request.app.state.backend  # writing minutes of every topic takes seconds: its own deadline
    reply = await backend.reply_query("recorder/save", BlackBoxSaveRequest(reason="hmi"),
                                      timeout_s=backend.config.blackbox_save_timeout_s)
    return BlackBoxSaved(ok=True, message=reply.message)


ROUTES = [blackbox_list, blackbox_download, blackbox_save]
