// A client of `lungdyn demo --igtl-serve` built on the OpenIGTLink C++ library — the library 3D
// Slicer's OpenIGTLinkIF links — so lungdyn's stream is decoded by the reference implementation of
// the protocol, not by lungdyn's code nor pyigtl's. bench/igtl_reference.sh builds and runs it.
//
// usage: receive PORT FRAMES OUT_JSON            connect to lungdyn's server (--igtl-serve PORT)
//        receive --listen PORT FRAMES OUT_JSON   listen, as Slicer's Server connector, for
//                                                `lungdyn demo --igtl-connect 127.0.0.1:PORT`
//
// Connects (waiting for the port while the demo bakes), reads FRAMES frames — a frame ends at the
// "BreathState" STRING — unpacking every body with the library's CRC-64 check, and writes one JSON
// object in the capture format of tests/peers/slicer_client.py (so the same Rust test holds it
// against the renderer's CPU reference): per frame its tick, device order, types and timestamps, and
// three frames (first, middle, last) whole — points, polygons (first frame only), attributes, the
// transform, the state. A message whose CRC the library refuses is counted in "crc_errors".
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>
#include <unistd.h>

#include "igtlClientSocket.h"
#include "igtlServerSocket.h"
#include "igtlMessageHeader.h"
#include "igtlPolyDataMessage.h"
#include "igtlStringMessage.h"
#include "igtlTransformMessage.h"
#include "igtlOSUtil.h"

namespace {

std::string quoted(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

std::string number(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.9g", v);
  return buf;
}

struct Message {
  std::string device, type;
  double timestamp = 0;
  std::string whole;  // the message as JSON (kept frames only)
  std::string polygons;
  std::string state;  // the STRING's text
};

// The POLYDATA body as JSON: points, polygon count, attributes (and the polygons, kept aside).
std::string polydata_json(igtl::PolyDataMessage* m, std::string& polygons) {
  std::string s = "{\"type\": \"POLYDATA\", \"points\": [";
  igtl::PolyDataPointArray* pts = m->GetPoints();
  int n = pts ? pts->GetNumberOfPoints() : 0;
  for (int i = 0; i < n; ++i) {
    igtlFloat32 p[3];
    pts->GetPoint(i, p);
    for (int k = 0; k < 3; ++k) s += (i || k ? ", " : "") + number(p[k]);
  }
  igtl::PolyDataCellArray* polys = m->GetPolygons();
  unsigned int cells = polys ? polys->GetNumberOfCells() : 0;
  s += "], \"polygon_count\": " + std::to_string(cells);
  polygons = "[";
  bool first = true;
  for (unsigned int c = 0; c < cells; ++c) {
    unsigned int size = polys->GetCellSize(c);
    std::vector<igtlUint32> cell(size);
    polys->GetCell(c, cell.data());
    polygons += (first ? "" : ", ") + std::to_string(size);
    first = false;
    for (igtlUint32 v : cell) polygons += ", " + std::to_string(v);
  }
  polygons += "]";
  s += ", \"attributes\": [";
  for (int a = 0; a < m->GetNumberOfAttributes(); ++a) {
    igtl::PolyDataAttribute* at = m->GetAttribute(static_cast<igtl::PolyDataMessage::AttributeList::size_type>(a));
    unsigned int comps = at->GetNumberOfComponents();
    unsigned int size = at->GetSize();
    std::vector<igtlFloat32> data(static_cast<size_t>(size) * comps);
    at->GetData(data.data());
    s += std::string(a ? ", " : "") + "{\"type\": " + std::to_string(at->GetType()) +
         ", \"components\": " + std::to_string(comps) + ", \"name\": " + quoted(at->GetName()) +
         ", \"data\": [";
    for (size_t i = 0; i < data.size(); ++i) s += (i ? ", " : "") + number(data[i]);
    s += "]}";
  }
  return s + "]}";
}

}  // namespace

int main(int argc, char** argv) {
  bool listen = argc == 5 && std::strcmp(argv[1], "--listen") == 0;
  if (argc != 4 && !listen) {
    std::fprintf(stderr, "usage: %s [--listen] PORT FRAMES OUT_JSON\n", argv[0]);
    return 2;
  }
  if (listen) {
    ++argv;
  }
  int port = std::atoi(argv[1]);
  size_t frames = static_cast<size_t>(std::atol(argv[2]));
  igtl::Socket::Pointer socket;
  igtl::ServerSocket::Pointer server;
  if (listen) {
    server = igtl::ServerSocket::New();
    if (server->CreateServer(port) < 0) {
      std::fprintf(stderr, "receive: cannot listen on port %d\n", port);
      return 1;
    }
    // Wait up to 3 minutes for lungdyn (it bakes and starts its processes first).
    for (int i = 0; i < 180 && !socket; ++i) socket = server->WaitForConnection(1000);
    if (!socket) {
      std::fprintf(stderr, "receive: lungdyn never connected to port %d\n", port);
      return 1;
    }
  } else {
    igtl::ClientSocket::Pointer client = igtl::ClientSocket::New();
    // The demo bakes and starts its processes before it listens: wait for the port.
    int tries = 0;
    while (client->ConnectToServer("127.0.0.1", port) != 0) {
      if (++tries > 1200) {
        std::fprintf(stderr, "receive: nothing listens on 127.0.0.1:%d after 2 minutes\n", port);
        return 1;
      }
      igtl::Sleep(100);
    }
    socket = client;
  }
  std::vector<std::vector<Message>> captured;
  std::vector<Message> current;
  int crc_errors = 0;
  // Keep every frame's messages whole for now; only three are written whole.
  while (captured.size() < frames) {
    igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
    header->InitPack();
    bool timeout = false;
    igtlUint64 r = socket->Receive(header->GetPackPointer(), header->GetPackSize(), timeout);
    if (r != header->GetPackSize()) {
      std::fprintf(stderr, "receive: the server closed the connection after %zu frames\n", captured.size());
      return 1;
    }
    header->Unpack();
    Message msg;
    msg.device = header->GetDeviceName();
    msg.type = header->GetDeviceType();
    unsigned int sec = 0, frac = 0;
    header->GetTimeStamp(&sec, &frac);
    msg.timestamp = sec + frac / 4294967296.0;
    igtl::MessageBase::Pointer body;
    igtl::PolyDataMessage::Pointer poly;
    igtl::StringMessage::Pointer str;
    igtl::TransformMessage::Pointer tr;
    if (msg.type == "POLYDATA") {
      poly = igtl::PolyDataMessage::New();
      body = poly;
    } else if (msg.type == "STRING") {
      str = igtl::StringMessage::New();
      body = str;
    } else if (msg.type == "TRANSFORM") {
      tr = igtl::TransformMessage::New();
      body = tr;
    } else {
      std::fprintf(stderr, "receive: an unexpected %s message from %s\n", msg.type.c_str(), msg.device.c_str());
      return 1;
    }
    body->SetMessageHeader(header);
    body->AllocatePack();
    r = socket->Receive(body->GetPackBodyPointer(), body->GetPackBodySize(), timeout);
    if (r != body->GetPackBodySize()) {
      std::fprintf(stderr, "receive: a body cut short\n");
      return 1;
    }
    int c = body->Unpack(1);
    if (!(c & igtl::MessageHeader::UNPACK_BODY)) {
      ++crc_errors;
    } else if (poly) {
      msg.whole = polydata_json(poly, msg.polygons);
    } else if (str) {
      msg.state = str->GetString();
      msg.whole = "{\"type\": \"STRING\", \"string\": " + quoted(msg.state) + "}";
    } else if (tr) {
      igtl::Matrix4x4 m;
      tr->GetMatrix(m);
      msg.whole = "{\"type\": \"TRANSFORM\", \"matrix\": [";
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) msg.whole += (i || j ? ", " : "") + number(m[i][j]);
      msg.whole += "]}";
    }
    bool ends = msg.device == "BreathState";
    current.push_back(std::move(msg));
    if (ends) {
      captured.push_back(std::move(current));
      current.clear();
    }
  }
  socket->CloseSocket();
  size_t n = captured.size();
  std::string out = "{\"client\": \"OpenIGTLink C++ library\", \"crc_errors\": " +
                    std::to_string(crc_errors) + ", \"frames\": [";
  for (size_t i = 0; i < n; ++i) {
    const std::vector<Message>& f = captured[i];
    // The tick: the state's JSON "tick" field.
    const std::string& st = f.back().state;
    size_t at = st.find("\"tick\":");
    std::string tick = at == std::string::npos ? "null" : std::to_string(std::atoll(st.c_str() + at + 7));
    out += std::string(i ? ", " : "") + "{\"tick\": " + tick + ", \"order\": [";
    for (size_t k = 0; k < f.size(); ++k) out += (k ? ", " : "") + quoted(f[k].device);
    out += "], \"types\": [";
    for (size_t k = 0; k < f.size(); ++k) out += (k ? ", " : "") + quoted(f[k].type);
    out += "], \"timestamps\": [";
    for (size_t k = 0; k < f.size(); ++k) out += (k ? ", " : "") + number(f[k].timestamp);
    out += "]";
    if (i == 0 || i == n / 2 || i == n - 1) {
      out += ", \"messages\": {";
      for (size_t k = 0; k < f.size(); ++k) {
        std::string whole = f[k].whole;
        if (i == 0 && f[k].type == "POLYDATA") {
          whole.pop_back();
          whole += ", \"polygons\": " + f[k].polygons + "}";
        }
        out += (k ? ", " : "") + quoted(f[k].device) + ": " + (whole.empty() ? "null" : whole);
      }
      out += "}";
    }
    out += "}";
  }
  out += "]}\n";
  FILE* fp = std::fopen(argv[3], "w");
  if (!fp || std::fputs(out.c_str(), fp) < 0 || std::fclose(fp) != 0) {
    std::fprintf(stderr, "receive: cannot write %s\n", argv[3]);
    return 1;
  }
  return 0;
}
